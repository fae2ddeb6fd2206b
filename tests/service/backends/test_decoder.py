"""The CPU-arranged decoder pieces give transformers' numbers (the end-to-end check is in test_backend_clipseg)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import textured_image

torch = pytest.importorskip("torch")

from gcdtrav.service.backends import decoder as fast  # noqa: E402
from gcdtrav.service.backends import onednn  # noqa: E402
from gcdtrav.service.backends.clipseg import ClipSegBackend, TorchCompute  # noqa: E402

nn = torch.nn


def refined_upsampler(channels: int = 16) -> torch.nn.Module:
    """The layout of CLIPSeg rd64-refined's transposed_convolution, at a smaller width."""
    return nn.Sequential(
        nn.Conv2d(channels, channels, kernel_size=3, padding=1),
        nn.ReLU(),
        nn.ConvTranspose2d(channels, channels // 2, kernel_size=4, stride=4),
        nn.ReLU(),
        nn.ConvTranspose2d(channels // 2, 1, kernel_size=4, stride=4),
    )


@pytest.mark.parametrize(
    ("name", "module"),
    [
        ("refined", refined_upsampler()),
        ("plain (use_complex_transposed_convolution=False)", nn.ConvTranspose2d(16, 1, kernel_size=16, stride=16)),
        ("rectangular blocks, several channels out", nn.Sequential(nn.ConvTranspose2d(16, 3, (2, 3), (2, 3)))),
        ("two steps, no activation", nn.Sequential(nn.ConvTranspose2d(16, 4, 2, 2), nn.ConvTranspose2d(4, 2, 3, 3))),
        ("no bias", nn.ConvTranspose2d(16, 2, kernel_size=4, stride=4, bias=False)),
    ],
)
def test_patchwise_upsampler_equals_the_module(name: str, module: torch.nn.Module) -> None:
    torch.manual_seed(0)
    module = module.eval()
    grid = torch.randn(5, 16, 7, 6)
    upsampler = fast.PatchwiseUpsampler(module)
    assert upsampler.fallback is None and upsampler.steps, name
    with torch.inference_mode():
        expected, got = module(grid), upsampler(grid)
    assert got.shape == expected.shape
    torch.testing.assert_close(got, expected, atol=2e-5, rtol=1e-5)


def test_overlapping_transposed_convolution_runs_the_module_itself() -> None:
    torch.manual_seed(1)
    module = nn.Sequential(nn.Conv2d(8, 8, 3, padding=1), nn.ConvTranspose2d(8, 1, kernel_size=4, stride=2)).eval()
    upsampler = fast.PatchwiseUpsampler(module)
    mixed = fast.PatchwiseUpsampler(nn.Sequential(nn.ConvTranspose2d(8, 4, 2, 2), nn.ConvTranspose2d(4, 1, 4, 2)))
    assert mixed.fallback is not None  # a patchwise step followed by an overlapping one
    assert not upsampler.steps  # nothing to rearrange: the module runs as it is
    grid = torch.randn(2, 8, 5, 5)
    with torch.inference_mode():
        torch.testing.assert_close(upsampler(grid), module(grid))


@pytest.mark.parametrize("dtype", ["float32", "bfloat16"])
def test_fused_linear_relu_equals_linear_then_relu(dtype: str) -> None:
    torch.manual_seed(2)
    linear = nn.Linear(16, 64).to(getattr(torch, dtype))
    hidden = torch.randn(3, 11, 16, dtype=linear.weight.dtype)
    with torch.inference_mode():
        got = onednn.fused_linear_relu(linear.weight.dtype)(hidden, linear)
        expected = torch.relu(linear(hidden))
    assert got.shape == expected.shape and bool((got >= 0).all())
    torch.testing.assert_close(got, expected)


def test_fused_ops_fall_back_without_onednn(monkeypatch: pytest.MonkeyPatch, tiny_backend: ClipSegBackend) -> None:
    def missing(*_: object) -> None:
        raise RuntimeError("no oneDNN in this build")

    monkeypatch.setattr(torch.ops.mkldnn, "_linear_pointwise", missing)
    assert not onednn.onednn_has("relu", torch.float32) and not onednn.onednn_has("swish", torch.bfloat16)
    assert onednn.fused_linear_relu(torch.float32) is onednn.linear_then_relu
    layer = tiny_backend.model.clip.vision_model.encoder.layers[0]
    assert onednn.QuickGeluMLP.build(layer.layer_norm2, layer.mlp, torch.float32) is None


@pytest.mark.parametrize(("dtype", "tolerance"), [("float32", 1e-5), ("bfloat16", 0.05)])
def test_fused_quick_gelu_layer_equals_transformers_layer(
    tiny_backend: ClipSegBackend, dtype: str, tolerance: float
) -> None:
    import copy

    layer = copy.deepcopy(tiny_backend.model.clip.vision_model.encoder.layers[2]).to(getattr(torch, dtype))
    mlp = onednn.QuickGeluMLP.build(layer.layer_norm2, layer.mlp, getattr(torch, dtype))
    if not onednn.onednn_has("swish", getattr(torch, dtype)):
        # AVX2-only CPUs: oneDNN has no bf16 swish post-op, so the layer must fall back to transformers'.
        assert mlp is None
        pytest.skip(f"this CPU's oneDNN has no {dtype} swish post-op; fallback asserted instead")
    assert mlp is not None
    torch.manual_seed(4)
    hidden = torch.randn(2, 17, layer.layer_norm1.normalized_shape[0]).to(getattr(torch, dtype))
    with torch.inference_mode():
        expected, got = layer(hidden, None), onednn.clip_encoder_layer(layer, hidden, mlp)
    scale = float(expected.float().abs().max())
    assert float((got.float() - expected.float()).abs().max()) <= tolerance * scale
    assert onednn.clip_encoder_layer(layer, hidden, None).equal(expected)  # no fused MLP: transformers' layer


def test_backend_without_onednn_still_matches_transformers(
    tiny_model_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(onednn, "onednn_has", lambda attr, dtype: False)
    backend = ClipSegBackend(str(tiny_model_dir), keep_reference=True)
    compute = backend.compute
    assert isinstance(compute, TorchCompute)
    assert all(mlp is None for mlp in compute.trunk.fused_mlps)
    assert compute.decoder.linear_relu is onednn.linear_then_relu
    concepts = ["water", "grass", "asphalt road"]
    image = textured_image(90, 70, seed=3)
    np.testing.assert_allclose(
        backend.logits(image, backend.prepare(concepts)), backend.naive_logits(image, concepts), atol=1e-4, rtol=0
    )  # no rescaled quick-GELU here: the same operations as transformers, to the last bits


def test_runs_faster_picks_the_quicker_call() -> None:
    import time

    def slow() -> None:
        time.sleep(0.02)

    def quick() -> None:
        pass

    assert onednn.runs_faster(quick, slow) and not onednn.runs_faster(slow, quick)


@pytest.mark.parametrize("fused_wins", [True, False])
def test_fused_ops_are_used_only_where_measured_faster(
    tiny_model_dir: Path, monkeypatch: pytest.MonkeyPatch, fused_wins: bool
) -> None:
    """On an AVX2-only EPYC oneDNN's fused fp32 linears are slower than torch's own: the backend times both
    at build and keeps the faster; either way the logits are transformers'."""
    if not (onednn.onednn_has("swish", torch.float32) and onednn.onednn_has("relu", torch.float32)):
        pytest.skip("this torch build has no oneDNN fp32 swish/relu post-ops: nothing to choose between")
    timed: list[int] = []

    def decided(first: object, second: object, rounds: int = 3) -> bool:
        timed.append(rounds)
        return fused_wins

    monkeypatch.setattr(onednn, "runs_faster", decided)
    backend = ClipSegBackend(str(tiny_model_dir), keep_reference=True)
    compute = backend.compute
    assert isinstance(compute, TorchCompute) and len(timed) == 2  # the trunk's MLP and the decoder's fc1
    assert all((mlp is not None) is fused_wins for mlp in compute.trunk.fused_mlps)
    assert (compute.decoder.linear_relu is onednn.linear_then_relu) is not fused_wins
    concepts = ["water", "grass", "asphalt road"]
    image = textured_image(90, 70, seed=3)
    np.testing.assert_allclose(
        backend.logits(image, backend.prepare(concepts)), backend.naive_logits(image, concepts), atol=1e-3, rtol=0
    )
