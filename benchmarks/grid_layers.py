"""Time the grid's planner layers per grid update and size its messages (issue 25 items 3 and 6).

    python -m benchmarks.grid_layers                      # 9 rounds, 200 x 200 cells; prints a Markdown table
    python -m benchmarks.grid_layers --runs 15 --out benchmarks/grid-layers-mine.json
    python -m benchmarks.grid_layers --quick              # 20 x 20 cells, 2 rounds: a smoke check, not a measurement

A 200 x 200 grid (20 m at 0.1 m) with every cell known, 13 anchors (the paper's point masses, and every anchor
0.05 wide), each cell fused from 4 pixels of random softmax weights. Rows, per grid update:
- T and U: GroundGrid.layers, what every update computed before the planner's layers;
- every layer: service/grid/layers.py grid_layers (T, U, CVaR at alpha 0.1, P(T < 0.3), match, age), and with
  the costmap's lethal threshold apart from tau (one more P(T < tau) product);
- encode: the GridMessage (T, U, CVaR, p_below, match as 16-bit PNGs, counts and age), the GridMap CDR (7
  float32 layers), the Nav2 costmap (grading and OccupancyGrid CDR).
Bytes per message are printed for the same grid. The calls take turns round by round (service/backends/timing.py),
one warm-up round first; median and minimum in ms.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np
from gcdtrav.schemas.anchors import Anchor, AnchorSet, default_anchor_set
from gcdtrav.schemas.settings import GridSettings
from gcdtrav.service.backends.cpus import cpu_name
from gcdtrav.service.backends.timing import interleaved_ms
from gcdtrav.service.engine import gcd
from gcdtrav.service.grid.fusion import GridSpec, GroundGrid
from gcdtrav.service.grid.layers import GridLayers, grid_layers, nav2_costs
from gcdtrav.service.ros.cdr import occupancy_values_cdr
from gcdtrav.service.runtime.grids import GridOutputs
from gcdtrav.service.runtime.grids.encoding import encode_update

ALPHA, TAU, LETHAL_TAU = 0.1, 0.3, 0.1
GAUSSIAN_WIDTH = 0.05
CELLS, QUICK_CELLS = 200, 20
RESOLUTION = 0.1
PIXELS_PER_CELL = 4


def filled_grid(cells: int, anchors: AnchorSet, seed: int) -> GroundGrid:
    """Every cell known, fused from PIXELS_PER_CELL pixels of random softmax weights and match scores."""
    grid = GroundGrid(GridSpec(cells * RESOLUTION, RESOLUTION, 2.0, 30.0), len(anchors), origin=(0.0, 0.0))
    rng = np.random.default_rng(seed)
    centres = (np.indices((cells, cells)).reshape(2, -1).T[:, ::-1] + 0.5) * RESOLUTION  # (x, y) per cell
    points = np.repeat(centres, PIXELS_PER_CELL, axis=0)
    logits = rng.normal(0.0, 2.0, (len(anchors), len(points))).astype(np.float32)
    match = rng.uniform(0.0, 1.0, len(points))
    grid.add(points, gcd.softmax_weights(logits), 0.0, anchors, match)
    return grid


def widened(anchors: AnchorSet, width: float) -> AnchorSet:
    return AnchorSet(anchors=[Anchor(concept=a.concept, position=a.position, width=width) for a in anchors.anchors])


def grid_config(cells: int) -> GridSettings:
    intrinsics = {"fx": 500, "fy": 500, "cx": 320, "cy": 240, "width": 640, "height": 480}
    return GridSettings.model_validate(
        {"source": "bench", "intrinsics": intrinsics, "size_m": cells * RESOLUTION, "resolution_m": RESOLUTION}
        | {"grid_map": True, "costmap": True}
    )


def calls(cells: int) -> tuple[dict[str, Callable[[], object]], dict[str, int]]:
    rows: dict[str, Callable[[], object]] = {}
    point_masses = default_anchor_set()
    for label, anchors in (("point masses", point_masses), (f"width {GAUSSIAN_WIDTH}", widened(point_masses, 0.05))):
        grid = filled_grid(cells, anchors, 1)
        positions, widths = np.asarray(anchors.positions), np.asarray(anchors.widths)
        rows[f"T and U only, {label}"] = partial(grid.layers, positions, widths)
        rows[f"every layer, {label}"] = partial(grid_layers, grid, positions, widths, ALPHA, TAU)
        rows[f"every layer + lethal P(T < {LETHAL_TAU}), {label}"] = partial(
            grid_layers, grid, positions, widths, ALPHA, TAU, LETHAL_TAU
        )
    # encoding does not depend on the anchors' widths: the last grid's layers (Gaussian anchors) serve
    layers = grid_layers(grid, positions, widths, ALPHA, TAU, LETHAL_TAU)
    outputs = GridOutputs([grid_config(cells)], len(point_masses), "bench")
    source = outputs.sources["bench"]
    source.grid = grid
    header = outputs.header(source, point_masses.version)
    config = source.config

    def encode_message(layers: GridLayers) -> bytes:
        return encode_update(
            config.model_copy(update={"grid_map": False, "costmap": False}), header, layers, None
        ).message.pack()

    def encode_grid_map(layers: GridLayers) -> bytes | None:
        return encode_update(config.model_copy(update={"costmap": False}), header, layers, None).grid_map

    def costmap(layers: GridLayers) -> bytes:
        return occupancy_values_cdr(header, nav2_costs(layers, config.lethal_probability, config.min_match))

    rows["encode GridMessage (6 PNGs)"] = partial(encode_message, layers)
    rows["encode GridMap CDR (7 float32 layers) + GridMessage"] = partial(encode_grid_map, layers)
    rows["Nav2 costmap: grade + OccupancyGrid CDR"] = partial(costmap, layers)
    update = encode_update(config, header, layers, None)
    sizes = {
        "GridMessage (msgpack)": len(update.message.pack()),
        "GridMap CDR": len(update.grid_map or b""),
        "costmap OccupancyGrid CDR": len(update.costmap or b""),
    }
    return rows, sizes


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=9, help="timed rounds (after one warm-up round)")
    parser.add_argument("--quick", action="store_true", help="tiny sizes and 2 rounds: checks the script runs")
    parser.add_argument("--out", type=Path, default=None, help="write the results as JSON")
    args = parser.parse_args(argv)
    cells, runs = (QUICK_CELLS, 2) if args.quick else (CELLS, args.runs)
    rows_to_time, sizes = calls(cells)
    times = interleaved_ms(rows_to_time, rounds=runs)
    machine = {"cpu": cpu_name(), "python": platform.python_version(), "numpy": np.__version__}
    print(
        f"{machine['cpu']}, Python {machine['python']}, numpy {machine['numpy']}; {cells} x {cells} cells, "
        f"13 anchors, {runs} rounds" + (" (quick)" * args.quick)
    )
    print("| row | median ms | min ms |")
    print("|---|---|---|")
    rows = []
    for name, ms in times.items():
        rows.append({"row": name, "median_ms": statistics.median(ms), "min_ms": min(ms), "runs_ms": ms})
        print(f"| {name} | {statistics.median(ms):.1f} | {min(ms):.1f} |")
    print()
    print("| message | bytes per update |")
    print("|---|---|")
    for name, size in sizes.items():
        print(f"| {name} | {size} |")
    if args.out:
        result = {"machine": machine, "quick": args.quick, "rounds": runs, "cells": cells, "rows": rows}
        args.out.write_text(json.dumps(result | {"bytes": sizes}, indent=2) + "\n", "utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
