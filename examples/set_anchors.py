"""An operator swapping the service's anchor set at runtime (no restart).

python examples/set_anchors.py my_anchors.yaml [-e tcp/HOST:7447]     # swap
python examples/set_anchors.py                                        # show the active set
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from gcdtrav.client import AnchorSetRejected, TraversabilityClient, add_zenoh_arguments, zenoh_config_from_args
from gcdtrav.schemas.anchors import AnchorSet, AnchorSetError


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("file", nargs="?", type=Path, help="anchor set (JSON or YAML); omit to show the active one")
    add_zenoh_arguments(parser)
    args = parser.parse_args()
    with TraversabilityClient(config=zenoh_config_from_args(args)) as client:
        if args.file is None:
            active = client.anchors()
            print(f"active anchor set {active.version}:\n{active.anchor_set.to_json()}")
            return 0
        try:
            anchors = AnchorSet.load(args.file)  # validate locally first: clearer errors, no round trip
            version = client.set_anchors(anchors)
        except (AnchorSetError, AnchorSetRejected) as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
    print(f"anchor set {version} is active")
    return 0


if __name__ == "__main__":
    sys.exit(main())
