"""The attention kernels this machine has, at CLIPSeg's two attention shapes, against the floor's best rate.

    python -m benchmarks.attention_kernels [--threads 2] [--runs 20] [--concepts 2] [--out FILE.json]

Attention is most of the distance between a frame and this machine's floor (issue 60): the floor counts its
token-by-token products at the best rate the machine runs any product (int8), while every runtime gcdtrav has
runs them in fp32. This times, for one layer of the vision transformer (12 heads of 64 at 485 tokens) and one
of the decoder (4 heads of 16, for ``--concepts`` concepts at once), each kernel there is:
- ONNX Runtime's fused ``MultiHeadAttention`` in fp32, the one gcdtrav's exports run;
- torch's ``scaled_dot_product_attention`` in fp32 and in bf16;
- OpenVINO's, in f32 and bf16, where ``openvino`` is installed (it is not a gcdtrav dependency).
Each kernel's calls run back to back after a warm-up: taking turns, one runtime's threads still awake from its
call slowed the next runtime's (torch's fp32 attention 3.9 -> 12.6 ms). Each row gives the median, the rate
it means and its multiple of the time at the floor's best rate (int8, ONNX Runtime's MatMulInteger at the
vision transformer's shapes, measured first).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import statistics
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from gcdtrav.service.backends.cpus import cpu_features, cpu_name
from gcdtrav.service.backends.floor import TrunkShape, measure_floors
from gcdtrav.service.backends.onnx_runtime import session_options
from gcdtrav.service.backends.timing import interleaved_ms

WARMUP = 3


@dataclass(frozen=True)
class AttentionShape:
    name: str
    batch: int
    heads: int
    tokens: int
    head_width: int

    @property
    def flops(self) -> float:
        """The scores and the weighted values: two (tokens x head_width x tokens) products per head."""
        return 4.0 * self.batch * self.heads * self.tokens**2 * self.head_width

    def inputs(self) -> list[torch.Tensor]:
        """Q, K and V as (batch, heads, tokens, head_width)."""
        generator = torch.Generator().manual_seed(0)
        size = (self.batch, self.heads, self.tokens, self.head_width)
        return [torch.randn(size, generator=generator) for _ in range(3)]


def rd64_shapes(concepts: int) -> list[AttentionShape]:
    """CLIPSeg rd64-refined at 352 px: 22 x 22 patches and the class token."""
    return [
        AttentionShape("vision transformer layer", 1, 12, 485, 64),
        AttentionShape(f"decoder layer, {concepts} concept{'s' if concepts != 1 else ''}", concepts, 4, 485, 16),
    ]


def torch_kernel(shape: AttentionShape, dtype: torch.dtype) -> Callable[[], object]:
    query, key, value = (tensor.to(dtype) for tensor in shape.inputs())

    def run() -> object:
        with torch.inference_mode():
            return torch.nn.functional.scaled_dot_product_attention(query, key, value)

    return run


def onnxruntime_kernel(shape: AttentionShape, threads: int) -> Callable[[], object]:
    """com.microsoft.MultiHeadAttention on (batch, tokens, width) projections, as gcdtrav's exports have it."""
    import onnxruntime
    from onnx import TensorProto, helper

    width = shape.heads * shape.head_width
    dims = [shape.batch, shape.tokens, width]
    node = helper.make_node("MultiHeadAttention", ["q", "k", "v"], ["y"], domain="com.microsoft", num_heads=shape.heads)
    names = ["q", "k", "v"]
    graph = helper.make_graph(
        [node],
        "attention",
        [helper.make_tensor_value_info(name, TensorProto.FLOAT, dims) for name in names],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, dims)],
    )
    opsets = [helper.make_opsetid("", 17), helper.make_opsetid("com.microsoft", 1)]
    model = helper.make_model(graph, opset_imports=opsets, ir_version=8)
    options = session_options(threads)  # gcdtrav's: its threads sleep between calls
    session = onnxruntime.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])
    feeds = {
        name: tensor.transpose(1, 2).reshape(dims).numpy() for name, tensor in zip(names, shape.inputs(), strict=True)
    }
    return lambda: session.run(None, feeds)


def openvino_kernel(shape: AttentionShape, precision: str, threads: int) -> Callable[[], object]:
    import openvino

    class Attention(torch.nn.Module):
        def forward(self, query: torch.Tensor, key: torch.Tensor, value: torch.Tensor) -> torch.Tensor:
            return torch.nn.functional.scaled_dot_product_attention(query, key, value)

    inputs = shape.inputs()
    model = openvino.convert_model(Attention(), example_input=tuple(inputs))
    config = {"INFERENCE_PRECISION_HINT": precision, "INFERENCE_NUM_THREADS": threads, "PERFORMANCE_HINT": "LATENCY"}
    request = openvino.Core().compile_model(model, "CPU", config).create_infer_request()
    feeds = [tensor.numpy() for tensor in inputs]
    return lambda: request.infer(feeds)


def kernels(shape: AttentionShape, threads: int) -> dict[str, Callable[[], object]]:
    """Every kernel this machine has for ``shape``; a runtime that is not installed is left out."""
    found: dict[str, Callable[[], object]] = {}
    with contextlib.suppress(ImportError):
        found["onnxruntime MultiHeadAttention fp32"] = onnxruntime_kernel(shape, threads)
    found["torch sdpa fp32"] = torch_kernel(shape, torch.float32)
    found["torch sdpa bf16"] = torch_kernel(shape, torch.bfloat16)
    with contextlib.suppress(ImportError):
        for precision in ("f32", "bf16"):
            found[f"openvino sdpa {precision}"] = openvino_kernel(shape, precision, threads)
    return found


def measure(shapes: list[AttentionShape], threads: int, runs: int, best_rate: float) -> list[dict[str, Any]]:
    rows = []
    for shape in shapes:
        at_floor_ms = 1000.0 * shape.flops / best_rate
        for kernel, call in kernels(shape, threads).items():
            ms = statistics.median(interleaved_ms({kernel: call}, runs, WARMUP)[kernel])
            rate = shape.flops / (ms / 1000.0)
            row = {"shape": shape.name, "kernel": kernel, "ms": ms, "gflops": rate / 1e9, "x_floor": ms / at_floor_ms}
            rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--concepts", type=int, default=2, help="concepts in one decoder run (gcdtrav's chunk: 2)")
    parser.add_argument("--out", type=Path, help="also write the rows and the machine as JSON")
    args = parser.parse_args(argv)
    threads_before = torch.get_num_threads()
    torch.set_num_threads(args.threads)
    try:
        shape = TrunkShape(tokens=485, hidden=768, mlp=3072, layers=1)
        best = max(floor.peak for floor in measure_floors(shape, {"int8", "fp32"}, args.threads))
        print(f"{cpu_name()}, {args.threads} threads; the floor's best rate: {best / 1e9:,.0f} G/s")
        rows = measure(rd64_shapes(args.concepts), args.threads, args.runs, best)
    finally:
        torch.set_num_threads(threads_before)
    print("| shape | kernel | ms | GFLOP/s | x its time at the floor's best rate |\n|---|---|---:|---:|---:|")
    for row in rows:
        print(f"| {row['shape']} | {row['kernel']} | {row['ms']:.3f} | {row['gflops']:,.0f} | {row['x_floor']:.1f} |")
    if args.out:
        machine = {"cpu": cpu_name(), "features": sorted(cpu_features()), "threads": args.threads}
        args.out.write_text(json.dumps({"machine": machine, "best_rate": best, "rows": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
