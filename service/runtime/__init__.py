"""Serving without middleware, in the frame's order: ``intake/`` admits, ``schedule/`` queues and picks,
``triage/`` glances, the worker infers and fuses into ``grids/``, ``outputs`` hands the payloads out; ``fleet/``
stands beside. Below the rooms: the frame's record (``frames``), the history and its answers, the counters.
``assembly`` wires it all once; ``service/bus`` wires it to zenoh."""
