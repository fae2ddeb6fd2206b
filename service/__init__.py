"""gcdtrav's server side: the GCD engine, model backends, the offline CLI and the Zenoh service.

Sub-packages are layered: ``engine`` (numpy only) <- ``backends`` (torch) <- ``bus`` (zenoh).
Nothing is imported here so that ``import gcdtrav.service.engine`` never pulls torch.
"""
