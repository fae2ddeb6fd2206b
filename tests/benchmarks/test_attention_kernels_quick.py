"""benchmarks/attention_kernels.py: each kernel computes the attention it is timed for, and the table and JSON
carry every kernel at both shapes; the figures are in benchmarks/README.md (issue 60)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmarks.attention_kernels import AttentionShape, main, measure, onnxruntime_kernel, rd64_shapes, torch_kernel

SMALL = AttentionShape("small", batch=2, heads=3, tokens=7, head_width=4)


def reference(shape: AttentionShape) -> torch.Tensor:
    """softmax(Q K^T / sqrt(d)) V, written out: (batch, heads, tokens, head_width)."""
    query, key, value = shape.inputs()
    scores = query @ key.transpose(-1, -2) / shape.head_width**0.5
    return torch.softmax(scores, dim=-1) @ value


def test_flops_count_both_products_of_every_head() -> None:
    assert SMALL.flops == 2 * (2 * 3 * 7 * 4 * 7) * 2  # scores and weighted values, a multiply-add two each
    vision, decoder = rd64_shapes(concepts=13)
    assert vision.flops * 10 == pytest.approx(7.22e9, rel=1e-3)  # the 10 layers' 7.2 GFLOP the floor counts
    assert decoder.batch == 13 and decoder.heads * decoder.head_width == 64


def test_the_kernels_compute_the_attention_they_are_timed_for() -> None:
    expected = reference(SMALL)
    assert torch.allclose(torch.as_tensor(torch_kernel(SMALL, torch.float32)()), expected, atol=1e-6)
    bf16 = torch.as_tensor(torch_kernel(SMALL, torch.bfloat16)()).float()
    assert torch.allclose(bf16, expected, atol=3e-2)
    pytest.importorskip("onnxruntime")
    (fused,) = onnxruntime_kernel(SMALL, threads=1)()  # type: ignore[misc]
    as_heads = torch.from_numpy(np.asarray(fused)).reshape(2, 7, 3, 4).transpose(1, 2)
    assert torch.allclose(as_heads, expected, atol=1e-5)


def test_rows_give_each_kernels_time_rate_and_multiple_of_the_floor() -> None:
    rows = measure([SMALL], threads=1, runs=1, best_rate=1e9)
    kernels = {row["kernel"] for row in rows}
    assert {"torch sdpa fp32", "torch sdpa bf16"} <= kernels
    for row in rows:
        assert row["ms"] > 0
        assert row["gflops"] == pytest.approx(SMALL.flops / (row["ms"] / 1e3) / 1e9)
        assert row["x_floor"] == pytest.approx(row["ms"] / (1e3 * SMALL.flops / 1e9))


def test_main_prints_both_shapes_and_writes_the_machine(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "attention.json"
    assert main(["--runs", "1", "--threads", "1", "--concepts", "1", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "the floor's best rate" in printed and "| vision transformer layer | torch sdpa fp32 |" in printed
    assert "| decoder layer, 1 concept | torch sdpa bf16 |" in printed
    written = json.loads(out.read_text())
    assert written["machine"]["threads"] == 1 and written["best_rate"] > 0
    assert {row["shape"] for row in written["rows"]} == {"vision transformer layer", "decoder layer, 1 concept"}
