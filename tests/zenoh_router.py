"""A zenoh router of the test's own, run as a process so that tests can kill and restart it.

python tests/zenoh_router.py PORT
"""

from __future__ import annotations

import os
import signal
import sys
import threading

import zenoh
from gcdtrav.client.session.zenoh_args import zenoh_config


def main() -> None:
    port = int(sys.argv[1])
    session = zenoh.open(zenoh_config(mode="router", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False))
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    print("router ready", flush=True)
    stop.wait(600)  # bounded: a test that forgets it does not leave it running for long
    # Closed politely if it can be (the clients hear of it), but never for long: loaded, a router's close or its
    # interpreter's exit once outlasted a test's 20 s teardown.
    closing = threading.Thread(target=session.close, daemon=True)
    closing.start()
    closing.join(5.0)
    sys.stdout.flush()
    os._exit(0)


if __name__ == "__main__":
    main()
