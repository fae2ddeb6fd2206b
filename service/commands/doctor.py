"""`gcdtrav doctor`: what to run first on a new box. The CPU and its features, the versions that matter,
whether the weights are found, this machine's floor for a frame (service/backends/floor.py), every precision
mode's time (and its multiple of the floor) and parity here, the mode auto picks, and the frames/s to expect."""

from __future__ import annotations

import argparse
import importlib.metadata
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.service.backends import ModelUnavailableError, default_model
from gcdtrav.service.backends.cpus import (
    amx_tiles_offered,
    cpu_features,
    cpu_name,
    set_torch_threads,
    usable_cpus,
    xcomp_supported,
)

EXIT_OK, EXIT_NO_WEIGHTS = 0, 1
PACKAGES = ("torch", "transformers", "onnxruntime", "onnx", "eclipse-zenoh", "numpy", "opencv-python-headless")


def build_parser(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    parser.add_argument("--model", help="CLIPSeg checkpoint directory or hub id [env GCDTRAV_MODEL, else the hub id]")
    parser.add_argument("--runs", type=int, default=3, help="timed frames per mode [3]")
    parser.add_argument(
        "--cache-dir",
        type=Path,
        help="where ONNX exports and the measurement are kept, shared with infer and serve "
        "[$XDG_CACHE_HOME/gcdtrav, else ~/.cache/gcdtrav]",
    )
    parser.add_argument(
        "--measure",
        action="store_true",
        help="measure the modes again even if figures for this machine are cached (and cache the new ones)",
    )
    return parser


def version_of(package: str) -> str:
    try:
        return importlib.metadata.version(package)
    except importlib.metadata.PackageNotFoundError:
        return "not installed"


def machine_info() -> dict[str, Any]:
    """This machine as benchmarks and the doctor report it (the bench JSON's ``machine``)."""
    import torch
    from gcdtrav.service.backends.machine import cpu_has_fast_bf16

    features = cpu_features()
    return {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "onnxruntime": version_of("onnxruntime"),
        "cpu": cpu_name(),
        "cpu_features": features,
        "cores": os.cpu_count(),
        "usable_cores": usable_cpus(),
        "torch_threads": torch.get_num_threads(),
        "fast_bf16": cpu_has_fast_bf16(),
        "amx_tiles": amx_tiles_offered(features, xcomp_supported()),  # None: no AMX
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
    }


def machine_lines() -> list[str]:
    info = machine_info()
    bf16 = "yes (AVX512-BF16 or AMX)" if info["fast_bf16"] else "no: bf16 modes would be emulated"
    lines = [
        f"CPU          {info['cpu']} ({platform.machine()})",
        f"cores        {info['usable_cores']} usable by this process; torch threads {info['torch_threads']}",
        f"features     {' '.join(info['cpu_features']) or 'none of the ones that matter'}",
        f"native bf16  {bf16}",
    ]
    if info["amx_tiles"] is not None:
        lines.append(f"AMX tiles    {AMX_TILES[info['amx_tiles']]}")
    versions = ", ".join(f"{p} {version_of(p)}" for p in PACKAGES) + f", python {platform.python_version()}"
    return [*lines, f"versions     {versions}"]


AMX_TILES = {
    True: "offered by the kernel: AMX kernels can run",
    False: (
        "NOT offered by the kernel (a kernel before 5.16, or a VM that does not pass AMX's tile state "
        "through): no AMX kernel runs, bf16 and int8 fall back to AVX-512"
    ),
}


def run(args: argparse.Namespace) -> int:
    from gcdtrav.service.backends.clipseg import ClipSegBackend
    from gcdtrav.service.backends.machine import available_precisions
    from gcdtrav.service.backends.precision_choice import PARITY_P99_DT_LIMIT, cached_choice, measure_and_store

    set_torch_threads(None)  # as infer and serve do: the cached figures are keyed by the threads
    for line in machine_lines():
        print(line)
    model = args.model or default_model()
    try:
        backend = ClipSegBackend(model, precision="fp32", keep_reference=True, cache_dir=args.cache_dir)
    except ModelUnavailableError as err:
        print(f"weights      NOT FOUND: {err}")
        return EXIT_NO_WEIGHTS
    print(f"weights      found: {backend.checkpoint_dir or model}")
    modes = available_precisions()
    choice = None if args.measure else cached_choice(backend, modes)
    if choice is None:
        print(f"\ntiming {', '.join(modes)} ({args.runs} frames each, 13 anchors, {backend.preprocess.size} px) ...")
        sys.stdout.flush()
        choice = measure_and_store(backend, modes, runs=args.runs)
        print(f"(cached in {backend.cache_dir / 'precision'}: infer and serve run the mode picked below)")
    else:
        print(f"\nfigures of an earlier measurement on this machine, cached in {backend.cache_dir / 'precision'}")
        print("(gcdtrav doctor --measure measures again)")
    measured = choice.measurements
    floor_ms = print_floor(backend, modes)
    print(f"\n| mode | ms per frame | x floor | frames/s | p99 abs dT vs fp32 | parity (<= {PARITY_P99_DT_LIMIT}) |")
    print("|---|---:|---:|---:|---:|---|")
    for m in measured:
        if m.ms_per_frame is None or m.p99_dT is None:
            print(f"| {m.mode} | - | - | - | - | cannot run here: {m.error} |")
            continue
        verdict = "passes" if m.passes else "FAILS"
        multiple = f"{m.ms_per_frame / floor_ms:.1f}" if floor_ms else "-"
        frame = f"{m.ms_per_frame:.0f} | {multiple} | {1000 / m.ms_per_frame:.2f}"
        print(f"| {m.mode} | {frame} | {m.p99_dT:.4f} | {verdict} |")
    best = next(m for m in measured if m.mode == choice.mode)
    print(f"\nprecision auto picks {choice.mode} here.")
    if best.ms_per_frame:
        print(
            f"Expect about {1000 / best.ms_per_frame:.1f} frames/s of model time for all sources together "
            "(the GCD engine, decoding and encoding add a few ms per frame; gcdtrav bench measures them)."
        )
    return EXIT_OK


def print_floor(backend: Any, modes: list[str]) -> float | None:
    """Print this machine's floor for a frame's matrix products (the paper's anchors, as the modes were timed),
    per arithmetic the modes use; the lowest, ms."""
    import torch
    from gcdtrav.service.backends.floor import frame_shape, measure_floors
    from gcdtrav.service.backends.modes import runtime_mode

    threads = torch.get_num_threads()
    shape = frame_shape(backend.model, backend.vision_tokens, len(default_anchor_set().concepts))
    floors = measure_floors(shape, {runtime_mode(mode).trunk for mode in modes}, threads)
    parts = ", ".join(f"{name} {flops / 1e9:.3g}" for name, flops in shape.parts.items())
    print(
        f"\nfloor        {shape.matmul_flops / 1e9:.3g} GFLOP of matrix products a frame ({shape.concepts} anchors, "
        f"{shape.trunk.tokens} tokens: {parts}),\n             each at this machine's rate for its shape "
        f"({threads} threads; attention's at the best rate, as a fused kernel runs them):"
    )
    for floor in floors:
        unit = "GOP/s" if floor.arithmetic == "int8" else "GFLOP/s"
        stages = ", ".join(f"{name} {ms:.3g}" for name, ms in floor.stage_ms(shape).items())
        print(
            f"             {floor.arithmetic:<5} ({floor.runtime}) -> {floor.ms(shape):.3g} ms ({stages}); "
            f"all at its best rate, {floor.peak / 1e9:,.0f} {unit}: {floor.peak_ms(shape):.3g} ms"
        )
    lowest = min((floor.ms(shape) for floor in floors), default=None)
    if lowest is not None:
        print(f"             x floor below: a mode's frame over the lowest, {lowest:.3g} ms")
    return lowest
