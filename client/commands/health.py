"""Health check for containers and supervisors: exit 0 if this host's service instance answers its status
and reports itself healthy (its worker progresses: a stalled instance has left the fleet, see stall_after_s).

    python -m gcdtrav.client.commands.health -m client -e tcp/zenoh-router:7447 --no-multicast-scouting

The instance is found by name: ``--instance``, else $GCDTRAV_INSTANCE, else the default name the service
gives itself on this host (``{hostname}-{pid}``, matched by its ``{hostname}-`` prefix). Torch-free.
"""

from __future__ import annotations

import argparse
import os
import socket
import sys

from gcdtrav.client.client import ServiceError, TraversabilityClient
from gcdtrav.client.session.zenoh_args import add_zenoh_arguments, zenoh_config_from_args


def is_this_instance(name: str, wanted: str | None) -> bool:
    return name == wanted if wanted else name.startswith(f"{socket.gethostname()}-")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m gcdtrav.client.commands.health", description=__doc__.split("\n")[0]
    )
    add_zenoh_arguments(parser)
    parser.add_argument("--prefix", default="gcdtrav", help="the service's key prefix [gcdtrav]")
    parser.add_argument("--instance", default=os.environ.get("GCDTRAV_INSTANCE"), help="instance name to expect")
    parser.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for the status [5]")
    args = parser.parse_args(argv)
    try:
        with TraversabilityClient(config=zenoh_config_from_args(args), prefix=args.prefix) as client:
            statuses = client.statuses(timeout=args.timeout)
    except (ServiceError, ValueError) as err:
        print(f"unhealthy: {err}", file=sys.stderr)
        return 1
    mine = [status for status in statuses if is_this_instance(status.instance, args.instance)]
    if not mine:
        expected = args.instance or f"{socket.gethostname()}-*"
        names = [status.instance for status in statuses]
        print(f"unhealthy: instance {expected} did not answer (answered: {names or 'none'})", file=sys.stderr)
        return 1
    stalled = [status for status in mine if status.healthy is False]
    if stalled:
        for status in stalled:
            print(f"unhealthy: instance {status.instance} {status.reason}", file=sys.stderr)
        return 1
    print("healthy")
    return 0


if __name__ == "__main__":
    sys.exit(main())
