"""`gcdtrav view`: a live Foxglove view of the service (WebSocket server), its anchor set as Foxglove parameters,
and MCAP recording. Torch-free; needs the ``view`` extra (foxglove-sdk, mcap).

Modules: ``pictures`` (what is drawn, numpy/OpenCV only), ``grid_layers`` (the grid's layers and the Nav2
costmap as channels), ``frames`` (transforms, calibration, frustum), ``probe`` (the distribution pointed at),
``replay`` (log lines and questions for late viewers), ``layout`` (a layout per service), ``anchor_parameters``
(anchor set <-> parameters), ``latest`` (latest-only buffers), ``recorder`` (rotating MCAP files under a total
cap), ``json_schema`` (flat JSON schemas that viewers parse), ``viewer`` (zenoh in, Foxglove out), ``command``
(the command line).
Nothing is imported here, so ``gcdtrav --help`` never loads foxglove.
"""
