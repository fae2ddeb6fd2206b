"""The project's benchmark: `gcdtrav bench` plus the service rows, on random weights of the real architecture.

    python -m benchmarks.bench [--model DIR] [--runs 7] [--zenoh-frames 100] [--robots 1,4,8]

Without ``--model`` it builds random weights of CLIPSeg rd64-refined (ViT-B/16 at 352x352 plus the text
encoder): the outputs are meaningless, the compute is the real one. Its ONNX exports stay in the scratch
directory. After the model rows it times the service: end to end through zenoh on loopback, and
throughput with simulated robots against a `gcdtrav serve` process.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from gcdtrav.service.commands import bench

from tools.random_clipseg import save_random_clipseg
from tools.service_load import run_robots, run_zenoh


def build_parser() -> argparse.ArgumentParser:
    parser = bench.build_parser(argparse.ArgumentParser(prog="python -m benchmarks.bench", description=__doc__))
    parser.set_defaults(out=Path("benchmarks/results/bench.json"))
    parser.add_argument("--zenoh-frames", type=int, default=100, help="frames for the end-to-end row (0: skip)")
    parser.add_argument("--robots", default="1,4,8", help="simulated robot counts for the throughput rows [1,4,8]")
    parser.add_argument("--robot-fps", type=float, default=10.0, help="frames/s each simulated robot sends [10]")
    parser.add_argument("--robot-seconds", type=float, default=10.0, help="measured seconds per robot count [10]")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)

    def service_rows(session: bench.Bench, precision: str, skip: set[str]) -> None:
        if "zenoh" not in skip and args.zenoh_frames > 0:
            run_zenoh(session, precision, args.zenoh_frames)
        if "robots" not in skip:
            bench.log_line("service throughput with simulated robots (one instance, loopback):")
            counts = [int(n) for n in args.robots.split(",") if n.strip()]
            run_robots(session, precision, counts, args.robot_fps, args.robot_seconds)

    with tempfile.TemporaryDirectory() as scratch:
        cache_dir = None
        if not args.model:
            args.model = str(Path(scratch) / "clipseg-rd64-refined-random")
            bench.log_line("building random weights of the real architecture (CLIPSeg rd64-refined) ...")
            save_random_clipseg(Path(args.model), preset="rd64-refined", input_size=352)
            cache_dir = Path(scratch) / "cache"  # exports of random weights are of no use after this run
        return bench.run(args, cache_dir=cache_dir, more_rows=service_rows)


if __name__ == "__main__":
    sys.exit(main())
