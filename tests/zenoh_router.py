"""A zenoh router of the test's own, run as a process so that tests can kill and restart it.

python tests/zenoh_router.py PORT

SIGTERM ends it at once, by the kernel's default action: a handler that closed the session politely (and
later one bounded at 5 s, then os._exit) still outlasted a test's 20 s teardown in two loaded full runs. Its
clients learn of the end from the closed TCP connections, as they would from a crashed router.
"""

from __future__ import annotations

import os
import sys
import time

import zenoh
from gcdtrav.client.session.zenoh_args import zenoh_config


def main() -> None:
    port = int(sys.argv[1])
    _router = zenoh.open(  # held open until the process ends
        zenoh_config(mode="router", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    )
    print("router ready", flush=True)
    time.sleep(600)  # bounded: a test that forgets it does not leave it running for long
    os._exit(0)


if __name__ == "__main__":
    main()
