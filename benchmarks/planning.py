"""Time issue 25's risk layers and planner: what a grid update and a replan cost on this machine.

    python -m benchmarks.planning                         # 9 rounds; prints a Markdown table
    python -m benchmarks.planning --runs 15 --out benchmarks/planning-mine.json
    python -m benchmarks.planning --quick                 # tiny sizes, 2 rounds: a smoke check, not a measurement

Rows (13 anchors, weights from a seeded softmax of random logits):
- risk layers: service/engine/risk.py risk_measures (quantile, CVaR at alpha 0.1, P(T < 0.1)) on a 200 x 200
  grid and on a 352 x 352 map (CLIPSeg's), with the paper's zero-width anchors (point masses: exact from the
  shared table) and with every anchor 0.05 wide (Gaussians: the Newton refinement runs);
- plan: client/planning.py plan, corner to corner of the 200 x 200 grid, CVaR cost, on the first row's layers.
The calls take turns round by round (service/backends/timing.py), one warm-up round first; median and minimum in ms.
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
from gcdtrav.client.planning import plan
from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.service.backends.cpus import cpu_name
from gcdtrav.service.backends.timing import interleaved_ms
from gcdtrav.service.engine import gcd, risk
from numpy.typing import NDArray

ALPHA, TAU = 0.1, 0.1
GAUSSIAN_WIDTH = 0.05
GRID, MAP = 200, 352
QUICK_GRID, QUICK_MAP = 20, 35


def random_weights(size: int, anchors: int, seed: int) -> NDArray[np.float32]:
    logits = np.random.default_rng(seed).normal(0.0, 2.0, (anchors, size, size)).astype(np.float32)
    return gcd.softmax_weights(logits)


def calls(grid: int, image: int) -> dict[str, Callable[[], object]]:
    anchors = default_anchor_set()
    positions, point_masses = anchors.positions, anchors.widths
    gaussians = [GAUSSIAN_WIDTH] * len(anchors)
    grid_weights, map_weights = random_weights(grid, len(anchors), 1), random_weights(image, len(anchors), 2)
    measures = risk.risk_measures(grid_weights, positions, point_masses, ALPHA, TAU)
    mean, _ = gcd.mixture_mean_std(grid_weights, positions, point_masses)
    layers = {"traversability": mean, "cvar": measures.cvar, "p_below": measures.p_below}
    rows: dict[str, Callable[[], object]] = {}
    for size, weights in ((grid, grid_weights), (image, map_weights)):
        for label, widths in (("point masses", point_masses), (f"width {GAUSSIAN_WIDTH}", gaussians)):
            rows[f"risk layers {size}x{size}, {label}"] = partial(
                risk.risk_measures, weights, positions, widths, ALPHA, TAU
            )
    rows[f"plan {grid}x{grid} corner to corner, cvar"] = partial(plan, layers, (0, 0), (grid - 1, grid - 1), "cvar")
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=9, help="timed rounds (after one warm-up round)")
    parser.add_argument("--quick", action="store_true", help="tiny sizes and 2 rounds: checks the script runs")
    parser.add_argument("--out", type=Path, default=None, help="write the results as JSON")
    args = parser.parse_args(argv)
    grid, image, runs = (QUICK_GRID, QUICK_MAP, 2) if args.quick else (GRID, MAP, args.runs)
    times = interleaved_ms(calls(grid, image), rounds=runs)
    machine = {"cpu": cpu_name(), "python": platform.python_version(), "numpy": np.__version__}
    print(
        f"{machine['cpu']}, Python {machine['python']}, numpy {machine['numpy']}; {runs} rounds"
        + (" (quick)" * args.quick)
    )
    print("| row | median ms | min ms |")
    print("|---|---|---|")
    rows = []
    for name, ms in times.items():
        rows.append({"row": name, "median_ms": statistics.median(ms), "min_ms": min(ms), "runs_ms": ms})
        print(f"| {name} | {statistics.median(ms):.1f} | {min(ms):.1f} |")
    if args.out:
        result = {"machine": machine, "quick": args.quick, "rounds": runs, "alpha": ALPHA, "tau": TAU, "rows": rows}
        args.out.write_text(json.dumps(result, indent=2) + "\n", "utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
