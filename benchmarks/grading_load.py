"""Inference beside grading (issue 57, docs/calibration.md "At fleet scale"): the frame time of one instance's
pipeline while another thread of the same process grades calibration once every ``--period`` s (a report
that takes longer starts the next at once: back to back), as a metrics scrape or an operator's watch would,
three ways in one run:

- **none**: no grading;
- **sums**: the report as the service answers it now (the kept sums, AUSE and Spearman over 10,000 pairs);
- **direct**: the figures computed over every raw pair, as a report did before the sums.

    python -m benchmarks.grading_load --model /tmp/rd64-random --pairs 1000000 --frames 30 --period 1

The store is SQLite (benchmarks/store.py's pairs); the model random weights of the real architecture
(``tools.random_clipseg``), in the precision given (ort-int8: auto's pick on AVX512 EPYCs). Medians and p95 of
the frames' wall time; the grading loop's reports per second beside them. The CPU is named in the output.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # benchmarks.store's throw-away cluster
from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.schemas.config import EngineSettings
from gcdtrav.service.backends.cpus import set_torch_threads
from gcdtrav.service.pipeline import clipseg_pipeline
from gcdtrav.service.store.sqlite import SqliteStore

from benchmarks.store import ANCHORS, TAU, calibrate, fill_to, machine, reporter


def frames(process: Callable[[], object], count: int) -> list[float]:
    times = []
    for _ in range(count):
        began = time.perf_counter()
        process()
        times.append(1000 * (time.perf_counter() - began))
    return times


def beside(
    grade: Callable[[], object] | None, process: Callable[[], object], count: int, period_s: float
) -> dict[str, float]:
    """The frames' median and p95 (ms) while ``grade`` runs every ``period_s`` on another thread; its reports/s."""
    stop, graded = threading.Event(), [0]

    def loop() -> None:
        while not stop.is_set():
            began = time.perf_counter()
            assert grade is not None
            grade()
            graded[0] += 1
            stop.wait(max(0.0, period_s - (time.perf_counter() - began)))

    worker = threading.Thread(target=loop, daemon=True) if grade is not None else None
    began = time.perf_counter()
    if worker is not None:
        worker.start()
    times = frames(process, count)
    stop.set()
    if worker is not None:
        worker.join()
    elapsed = time.perf_counter() - began
    return {
        "median_ms": statistics.median(times),
        "p95_ms": float(np.percentile(times, 95)),
        "reports_per_s": graded[0] / elapsed,
    }


def run(model: str, precision: str, pairs: int, count: int, period_s: float) -> dict[str, Any]:
    set_torch_threads(None)
    pipeline = clipseg_pipeline(model, precision, default_anchor_set(), EngineSettings())
    image = np.random.default_rng(0).integers(0, 256, (480, 640, 3), np.uint8)
    process = lambda: pipeline.process(image)  # noqa: E731
    frames(process, 3)  # warm-up
    with tempfile.TemporaryDirectory(prefix="gcdtrav-grading-") as folder:
        store = SqliteStore(Path(folder) / "store.sqlite3")
        fill_to(store, pairs, np.random.default_rng(0))
        reports = reporter(store)
        reports.report(ANCHORS, TAU)  # the sums caught up
        result = {
            "machine": machine(),
            "precision": precision,
            "pairs": pairs,
            "frames": count,
            "period_s": period_s,
            "none": beside(None, process, count, period_s),
            "sums": beside(lambda: reports.report(ANCHORS, TAU), process, count, period_s),
            "direct": beside(lambda: calibrate(store), process, count, period_s),
        }
        store.close()
    return result


def table(result: dict[str, Any]) -> str:
    m = result["machine"]
    lines = [
        f"{m['cpu']}, {m['cores']} cores; {result['precision']}; {result['pairs']:,} pairs; "
        f"{result['frames']} frames per row; a report every {result['period_s']:g} s (or back to back)",
        "",
        "| grading beside inference | frame median, ms | frame p95, ms | reports/s |",
        "|---|---:|---:|---:|",
    ]
    for name in ("none", "sums", "direct"):
        row = result[name]
        lines.append(f"| {name} | {row['median_ms']:.1f} | {row['p95_ms']:.1f} | {row['reports_per_s']:.2f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", required=True, help="a checkpoint directory (random weights: tools.random_clipseg)")
    parser.add_argument("--precision", default="ort-int8")
    parser.add_argument("--pairs", type=int, default=1_000_000)
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--period", type=float, default=1.0, help="a report every PERIOD s [1]")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    result = run(args.model, args.precision, args.pairs, args.frames, args.period)
    print(table(result))
    if args.out is not None:
        args.out.write_text(json.dumps(result, indent=1), "utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
