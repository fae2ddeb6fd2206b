"""A planner asking the ground grid for the worst cell on a path (metres, in the grid's frame).

    python examples/planner_path.py --source cam --path "0,0;3,0;5,2" [-e tcp/HOST:7447]

The service needs a grid for the source (settings `grids:`, see docs/grid.md).
"""

from __future__ import annotations

import argparse
import sys

from gcdtrav.client import ServiceError, TraversabilityClient, add_zenoh_arguments, zenoh_config_from_args
from gcdtrav.schemas.messages import ContextDistribution

MOSTLY = 0.5  # "mostly X" only when X holds at least half of the cell's weight


def parse_path(text: str) -> list[tuple[float, float]]:
    points = []
    for part in text.split(";"):
        x, y = (float(v) for v in part.split(","))
        points.append((x, y))
    return points


def ground_of(cell: ContextDistribution) -> str:
    """The ground of a cell: "mostly 'grass' (71%)" when one anchor holds half its weight or more, else the
    leading anchors with theirs (a cell of a dozen anchors at 8% each is not "mostly" anything)."""
    top = cell.top_anchors[:3]
    if not top:
        return "no anchors"
    first = top[0]
    if cell.weights[first] >= MOSTLY:
        return f"mostly '{cell.anchors[first].concept}' ({cell.weights[first]:.0%})"
    return "mixed: " + ", ".join(f"'{cell.anchors[k].concept}' {cell.weights[k]:.0%}" for k in top)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--source", default="cam")
    parser.add_argument("--path", required=True, help="x0,y0;x1,y1;... in metres")
    parser.add_argument("--max-uncertainty", type=float, default=0.25, help="flag cells whose U is above this")
    add_zenoh_arguments(parser)
    args = parser.parse_args()
    try:
        points = parse_path(args.path)
    except ValueError:
        parser.error("--path must be x0,y0;x1,y1;... in metres")
    with TraversabilityClient(config=zenoh_config_from_args(args)) as client:
        try:
            reply = client.path(args.source, points)
        except ServiceError as err:
            print(f"error: {err}", file=sys.stderr)
            return 1
    print(f"path {points}: {len(reply.cells)} known cells, {reply.unknown_cells} unknown")
    if reply.lowest_t is None or reply.highest_u is None:
        print("no known cell on this path: nothing seen there yet")
        return 0
    worst, doubt = reply.cells[reply.lowest_t], reply.cells[reply.highest_u]
    print(
        f"worst cell   {worst.cell_xy}: T {worst.mean:.2f} ({ground_of(worst)}), U {worst.std:.2f}, "
        f"{worst.observations} pixels"
    )
    print(f"most unsure  {doubt.cell_xy}: T {doubt.mean:.2f}, U {doubt.std:.2f}")
    risky = [c for c in reply.cells if c.std > args.max_uncertainty]
    print(f"{len(risky)} cells with U > {args.max_uncertainty}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
