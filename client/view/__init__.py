"""`gcdtrav view`: a live Foxglove view of the service (WebSocket server), its anchor set as Foxglove parameters,
and MCAP recording. Torch-free; needs the ``view`` extra (foxglove-sdk, mcap).

Modules: ``pictures`` (what is drawn, numpy/OpenCV only), ``anchor_parameters`` (anchor set <-> parameters),
``latest`` (latest-only buffers), ``recorder`` (rotating MCAP files under a total cap), ``json_schema`` (flat
JSON schemas that viewers parse), ``viewer`` (zenoh in, Foxglove out), ``command`` (the command line).
Nothing is imported here, so ``gcdtrav --help`` never loads foxglove.
"""
