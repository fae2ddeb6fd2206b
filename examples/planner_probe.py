"""A planner asking the service for the context distribution under a pixel, and printing it.

python examples/planner_probe.py --source r1/front --x 320 --y 400 [--region X0,Y0,X1,Y1] [-e tcp/HOST:7447]
"""

from __future__ import annotations

import argparse
import sys

from gcdtrav.client import ServiceError, TraversabilityClient, add_zenoh_arguments, zenoh_config_from_args
from gcdtrav.client.commands.density_plot import describe  # `gcdtrav probe SOURCE X Y` prints the same


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--source", default="r1/front")
    parser.add_argument("--x", type=float, default=None, help="image pixel column")
    parser.add_argument("--y", type=float, default=None, help="image pixel row")
    parser.add_argument("--region", default=None, help="X0,Y0,X1,Y1 in image pixels: pooled distribution")
    parser.add_argument("--seq", type=int, default=None, help="a kept frame [default: the latest]")
    parser.add_argument("--timeout", type=float, default=5.0)
    add_zenoh_arguments(parser)
    args = parser.parse_args()
    if args.region is None and (args.x is None or args.y is None):
        parser.error("give --x and --y, or --region")

    with TraversabilityClient(config=zenoh_config_from_args(args), timeout=args.timeout) as client:
        try:
            if args.region is not None:
                x0, y0, x1, y1 = (float(v) for v in args.region.split(","))
                reply = client.region(args.source, x0, y0, x1, y1, seq=args.seq)
            else:
                reply = client.patch(args.source, args.x, args.y, seq=args.seq)
        except ServiceError as err:
            print(f"error: {err}", file=sys.stderr)
            return 1
    print(describe(reply, None if args.region is not None else (args.x, args.y)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
