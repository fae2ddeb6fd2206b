"""Modes compared frame by frame, interleaved in one process: steadier ratios on a noisy machine.

    python -m benchmarks.interleaved --model DIR --modes fp32,ort-int8,ort-int8-vit --rounds 15

Without ``--model``: random weights of the real rd64-refined architecture. Each round runs one frame of
every mode in turn (13 anchors, 640x480 image), so drift of the machine hits all modes alike; the first
round is a warm-up. Prints the median and minimum per mode and its ratio to the first mode.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from functools import partial
from pathlib import Path

from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.service.backends.clipseg import ClipSegBackend
from gcdtrav.service.backends.precision_choice import synthetic_image
from gcdtrav.service.backends.timing import interleaved_ms
from gcdtrav.service.commands.bench import machine_header
from gcdtrav.service.commands.doctor import machine_info

from tools.random_clipseg import checkpoint_or_random


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", type=Path, default=None)
    parser.add_argument("--modes", default="fp32,ort-int8,ort-int8-vit")
    parser.add_argument("--rounds", type=int, default=15)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as scratch:
        model = checkpoint_or_random(args.model, Path(scratch))
        backend = ClipSegBackend(str(model), precision="fp32", keep_reference=True, cache_dir=Path(scratch) / "cache")
        modes = [m for m in args.modes.split(",") if m]
        computes = {mode: backend.compute_for(mode) for mode in modes}
        image, prepared = synthetic_image(), backend.prepare(default_anchor_set().concepts)

        def frame(mode: str) -> None:
            backend.use_compute(computes[mode], mode)  # an attribute swap: nothing to time
            backend.logits(image, prepared)

        times = interleaved_ms({mode: partial(frame, mode) for mode in modes}, args.rounds)
    print(machine_header(machine_info()))
    first = statistics.median(times[modes[0]])
    for mode in modes:
        median = statistics.median(times[mode])
        print(f"{mode:14s} median {median:7.1f} ms  min {min(times[mode]):7.1f} ms  {first / median:5.2f}x {modes[0]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
