"""Serving without middleware: frames, the worker, the history, the latest-only queue, sources, counters, the
anchor switch, admission, what is published and answered. ``service/bus`` wires it to zenoh."""
