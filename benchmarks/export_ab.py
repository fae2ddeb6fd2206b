"""An older ONNX export of the same checkpoint against this tree's, int8 trunk and decoder, frame by frame in
one process.

    python -m benchmarks.export_ab BEFORE_DIR AFTER_DIR [--before-chunk 8] [--rounds 15]

Each directory is an export as the service caches it (``<cache>/onnx/<key>/``), BEFORE for example one made
by an older commit in a worktree, AFTER one made by this tree. BEFORE runs as the older code ran it: one
session for the trunk, one for the decoder over 13 concepts in chunks of ``--before-chunk`` (fed the
trunk's outputs, or its reduction graph's where the export has one). AFTER runs as the service runs it now,
through ``OrtCompute``. A round runs one frame of each in turn, so drift of the machine hits both alike; the
first round is a warm-up. The inputs are random: the cost does not depend on the values. Prints medians and
the ratio after / before.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from gcdtrav.service.backends.cpus import cpu_features, cpu_name
from gcdtrav.service.backends.onnx_runtime import (
    DECODER_INT8,
    REDUCTION,
    TRUNK_INT8,
    ExportedModel,
    OrtCompute,
    concept_logits,
    session_options,
)

CONCEPTS, CONDITIONAL_WIDTH, SIZE = 13, 512, 352


def _session(path: Path, threads: int) -> Any:
    import onnxruntime as ort

    return ort.InferenceSession(str(path), session_options(threads), providers=["CPUExecutionProvider"])


def legacy_runner(directory: Path, chunk: int, threads: int) -> dict[str, Callable[[], object]]:
    """The export's trunk and decoder as two callables on fixed random inputs, each one session. An export
    without a reduction graph (before format 5) reduces inside the decoder: it is fed the trunk's outputs."""
    trunk, decoder = _session(directory / TRUNK_INT8, threads), _session(directory / DECODER_INT8, threads)
    reduction = _session(directory / REDUCTION, threads) if (directory / REDUCTION).exists() else None
    rng = np.random.default_rng(0)
    pixels = rng.standard_normal((1, 3, SIZE, SIZE)).astype(np.float32)
    conditional = rng.standard_normal((CONCEPTS, CONDITIONAL_WIDTH)).astype(np.float32)
    activations = trunk.run(None, {"pixels": pixels})

    def decode() -> object:
        inputs = activations
        if reduction is not None:
            names = [item.name for item in reduction.get_inputs()]
            inputs = reduction.run(None, dict(zip(names, activations, strict=True)))
        feeds = {item.name: value for item, value in zip(decoder.get_inputs(), inputs, strict=False)}
        chunks = []
        for start in range(0, CONCEPTS, chunk):
            feeds["conditional"] = conditional[start : start + chunk]
            chunks.append(decoder.run(None, feeds)[0])
        return concept_logits(chunks)

    return {"trunk": lambda: trunk.run(None, {"pixels": pixels}), "decoder": decode}


def product_runner(directory: Path, threads: int) -> dict[str, Callable[[], object]]:
    """The export run by ``OrtCompute``, as the service runs ort-int8."""
    compute = OrtCompute(ExportedModel(directory, {}), int8_trunk=True, int8_decoder=True, threads=threads)
    rng = np.random.default_rng(0)
    pixels = torch.from_numpy(rng.standard_normal((1, 3, SIZE, SIZE)).astype(np.float32))
    conditional = torch.from_numpy(rng.standard_normal((CONCEPTS, CONDITIONAL_WIDTH)).astype(np.float32))
    activations = compute.activations(pixels)
    return {"trunk": lambda: compute.activations(pixels), "decoder": lambda: compute.decode(activations, conditional)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("before", type=Path)
    parser.add_argument("after", type=Path)
    parser.add_argument("--before-chunk", type=int, default=8)
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    runners = {
        "before": legacy_runner(args.before, args.before_chunk, args.threads),
        "after": product_runner(args.after, args.threads),
    }
    times: dict[tuple[str, str], list[float]] = {}
    for round_index in range(args.rounds + 1):
        for name, parts in runners.items():
            for part, run in parts.items():
                start = time.perf_counter()
                run()
                if round_index:  # the first round warms up
                    times.setdefault((name, part), []).append((time.perf_counter() - start) * 1e3)
    print(f"cpu: {cpu_name()} ({' '.join(cpu_features())}), {args.threads} threads, {args.rounds} rounds")
    for part in ("trunk", "decoder", "frame"):
        medians = {}
        for name in runners:
            series = (
                [a + b for a, b in zip(times[(name, "trunk")], times[(name, "decoder")], strict=True)]
                if part == "frame"
                else times[(name, part)]
            )
            medians[name] = statistics.median(series)
        before, after = medians["before"], medians["after"]
        print(f"{part:8s} before {before:7.1f} ms  after {after:7.1f} ms  after/before {after / before:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
