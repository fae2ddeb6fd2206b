"""ONNX Runtime modes, their export cache, and precision auto chosen by measurement (tiny random-weight CLIPSeg)."""

from __future__ import annotations

import copy
import json
import logging
import re
from pathlib import Path

import numpy as np
import pytest
from conftest import textured_image

pytest.importorskip("torch")
pytest.importorskip("onnxruntime", reason="the ort-* modes need onnxruntime (in gcdtrav[service])")

from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.service.backends import onnx_runtime, precision_choice
from gcdtrav.service.backends.clipseg import ClipSegBackend, available_precisions
from gcdtrav.service.backends.onnx_runtime import TRUNK_INT8, OrtCompute
from gcdtrav.service.backends.precision_choice import PARITY_P99_DT_LIMIT, ModeMeasurement, parity, pick

ANCHORS = default_anchor_set()
IMAGE = textured_image(100, 120, seed=7)


def logits_of(backend: ClipSegBackend) -> np.ndarray:
    return backend.logits(IMAGE, backend.prepare(ANCHORS.concepts))


def export_dirs(cache: Path) -> list[Path]:
    return sorted(p for p in (cache / "onnx").iterdir() if not p.name.startswith("."))


@pytest.mark.parametrize("mode", ["ort-fp32", "ort-int8-vit", "ort-int8"])
def test_onnx_runtime_modes_match_torch_fp32(tiny_model_dir: Path, tiny_backend, tmp_path: Path, mode: str) -> None:  # type: ignore[no-untyped-def]
    backend = ClipSegBackend(str(tiny_model_dir), precision=mode, cache_dir=tmp_path)
    assert isinstance(backend.compute, OrtCompute) and backend.precision == mode
    reference, candidate = logits_of(tiny_backend), logits_of(backend)
    assert candidate.shape == reference.shape == (len(ANCHORS), 96, 96)
    if mode == "ort-fp32":  # the same arithmetic, reordered
        np.testing.assert_allclose(candidate, reference, atol=1e-4 * float(np.abs(reference).max()), rtol=0)
    else:
        assert float(np.abs(candidate - reference).max()) > 0  # int8 really ran
    assert parity(reference, candidate, ANCHORS)["p99_dT"] <= PARITY_P99_DT_LIMIT
    assert not [layer for layer in backend.model.clip.vision_model.encoder.layers]  # the torch ViT was released


def test_the_export_runs_each_attention_as_one_fused_node(tiny_model_dir: Path, tmp_path: Path) -> None:
    """Every layer's attention is one MultiHeadAttention node (no Softmax of its own); the decoder leaves its
    upsampled blocks nested, for OrtCompute.decode to put in image order once a frame."""
    import onnx
    from gcdtrav.service.backends.onnx_runtime import DECODER, TRUNK

    backend = ClipSegBackend(str(tiny_model_dir), precision="ort-fp32", cache_dir=tmp_path)
    [exported] = export_dirs(tmp_path)
    config = backend.model.config
    for name, layers in ((TRUNK, max(config.extract_layers) + 1), (DECODER, len(config.extract_layers))):
        graph = onnx.load(str(exported / name)).graph
        ops = [node.op_type for node in graph.node]
        assert ops.count("MultiHeadAttention") == layers and "Softmax" not in ops, name
    decoder_output = onnx.load(str(exported / DECODER)).graph.output[0].type.tensor_type.shape
    assert len(decoder_output.dim) > 3  # (concepts, h, w, kh1, kw1, ..., 1): nested blocks


def test_the_patch_embedding_as_one_product_is_clips_embedding(tiny_backend) -> None:  # type: ignore[no-untyped-def]
    """PatchEmbedding (the export's) against transformers' own embeddings at the input size, positions
    interpolated; a size the patches do not tile is refused."""
    import torch
    from gcdtrav.service.backends.onnx_graphs import PatchEmbedding

    embeddings = tiny_backend.model.clip.vision_model.embeddings
    size, patch = tiny_backend.preprocess.size, embeddings.patch_embedding.kernel_size[0]
    pixels = torch.randn(1, 3, size, size, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        expected = embeddings(pixels, interpolate_pos_encoding=True)
        found = PatchEmbedding(embeddings, size)(pixels)
    assert found.shape == expected.shape == (1, (size // patch) ** 2 + 1, embeddings.embed_dim)
    torch.testing.assert_close(found, expected, atol=1e-5, rtol=1e-5)
    with pytest.raises(ValueError, match=f"not tile {size + 1} px"):
        PatchEmbedding(embeddings, size + 1)
    for setting, value, says in (("padding", (1, 1), "padding (1, 1)"), ("dilation", (2, 2), "dilation (2, 2)")):
        changed = copy.deepcopy(embeddings)
        setattr(changed.patch_embedding, setting, value)
        with pytest.raises(ValueError, match=re.escape(says)):
            PatchEmbedding(changed, size)


def test_sessions_run_without_ort_s_skip_layer_norm_fusion(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """ONNX Runtime's own optimiser fuses an Add and the LayerNormalization after it into SkipLayerNormalization
    (a slower CPU kernel, onnx_runtime.DISABLED_OPTIMIZERS); gcdtrav's sessions keep them apart."""
    import onnx
    import onnxruntime as ort
    from onnx import TensorProto, helper, numpy_helper

    width = 8
    norm = [numpy_helper.from_array(np.ones(width, np.float32), name) for name in ("scale", "bias")]
    graph = helper.make_graph(
        [
            helper.make_node("Add", ["x", "skip"], ["sum"]),
            helper.make_node("LayerNormalization", ["sum", "scale", "bias"], ["y"], axis=-1),
        ],
        "residual",
        [helper.make_tensor_value_info(name, TensorProto.FLOAT, [1, 5, width]) for name in ("x", "skip")],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 5, width])],
        norm,
    )
    model = tmp_path / "residual.onnx"
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8), str(model))

    def optimised_ops(path: Path) -> list[str]:
        return [node.op_type for node in onnx.load(str(path)).graph.node]

    plain_options = onnx_runtime.session_options(1)
    plain_options.optimized_model_filepath = str(tmp_path / "plain.onnx")
    ort.InferenceSession(str(model), plain_options, providers=["CPUExecutionProvider"])
    options_of = onnx_runtime.session_options

    def writing_the_optimised_graph(threads: int) -> object:
        options = options_of(threads)
        options.optimized_model_filepath = str(tmp_path / "gcdtrav.onnx")
        return options

    monkeypatch.setattr(onnx_runtime, "session_options", writing_the_optimised_graph)
    session = onnx_runtime.inference_session(model, 1)
    assert optimised_ops(tmp_path / "plain.onnx") == ["SkipLayerNormalization"]  # the fusion applies here
    assert optimised_ops(tmp_path / "gcdtrav.onnx") == ["Add", "LayerNormalization"]
    x = np.arange(40, dtype=np.float32).reshape(1, 5, width)
    (y,) = session.run(None, {"x": x, "skip": x})
    centred = 2 * x - (2 * x).mean(axis=-1, keepdims=True)
    np.testing.assert_allclose(y, centred / np.sqrt((centred**2).mean(axis=-1, keepdims=True) + 1e-5) + 1, atol=1e-5)


@pytest.mark.parametrize("threads", [1, 3, 6])
def test_the_decoder_sessions_side_by_side_keep_the_concepts_in_order(
    tiny_model_dir: Path, tmp_path: Path, threads: int
) -> None:
    """One decoder session per thread up to DECODER_SESSIONS_MAX, chunks shared round-robin: 1 thread (no
    helpers), 3 (7 chunks of 13 concepts in shares of 3, 2, 2) and 6 (4 sessions) give the logits of the
    default compute, anchor by anchor."""
    from gcdtrav.service.backends.onnx_runtime import DECODER_SESSIONS_MAX, ExportedModel

    backend = ClipSegBackend(str(tiny_model_dir), precision="ort-fp32", cache_dir=tmp_path)
    [exported] = export_dirs(tmp_path)
    reference = logits_of(backend)
    backend.use_compute(OrtCompute(ExportedModel(exported, {}), False, False, threads=threads), "ort-fp32")
    assert len(backend.compute.decoders) == min(threads, DECODER_SESSIONS_MAX)
    np.testing.assert_allclose(logits_of(backend), reference, atol=1e-5 * float(np.abs(reference).max()), rtol=0)


def test_the_export_is_cached_and_a_corrupt_one_rebuilt(
    tiny_model_dir: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    first = logits_of(ClipSegBackend(str(tiny_model_dir), precision="ort-int8", cache_dir=tmp_path))
    [exported] = export_dirs(tmp_path)
    stamp = (exported / TRUNK_INT8).stat().st_mtime_ns
    ClipSegBackend(str(tiny_model_dir), precision="ort-int8", cache_dir=tmp_path)
    assert (exported / TRUNK_INT8).stat().st_mtime_ns == stamp  # reused, not rebuilt

    blob = bytearray((exported / TRUNK_INT8).read_bytes())
    blob[len(blob) // 2] ^= 0xFF  # one flipped byte inside the weights
    (exported / TRUNK_INT8).write_bytes(bytes(blob))
    with caplog.at_level(logging.WARNING):
        rebuilt = ClipSegBackend(str(tiny_model_dir), precision="ort-int8", cache_dir=tmp_path)
    assert "unusable (trunk-int8.onnx does not match its recorded hash); rebuilding it" in caplog.text
    np.testing.assert_array_equal(logits_of(rebuilt), first)
    assert export_dirs(tmp_path) == [exported]


def test_an_export_for_another_checkpoint_is_never_reused(tiny_model_dir: Path, tmp_path: Path) -> None:
    from conftest import build_tiny_clipseg

    other = build_tiny_clipseg(tmp_path / "other", seed=1)
    ClipSegBackend(str(tiny_model_dir), precision="ort-fp32", cache_dir=tmp_path / "cache")
    ClipSegBackend(str(other), precision="ort-fp32", cache_dir=tmp_path / "cache")
    assert len(export_dirs(tmp_path / "cache")) == 2
    keys = [json.loads((d / "manifest.json").read_text())["key"] for d in export_dirs(tmp_path / "cache")]
    assert keys[0]["checkpoint"] != keys[1]["checkpoint"] and keys[0]["cpu"] == keys[1]["cpu"]


def test_a_failed_export_is_a_clear_error_and_leaves_nothing_behind(
    tiny_model_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def broken(*args: object) -> None:
        raise RuntimeError("exporter exploded")

    monkeypatch.setattr(onnx_runtime, "_export", broken)
    with pytest.raises(onnx_runtime.ExportError, match="cannot export the model for ONNX Runtime: RuntimeError"):
        ClipSegBackend(str(tiny_model_dir), precision="ort-fp32", cache_dir=tmp_path)
    assert list((tmp_path / "onnx").iterdir()) == []  # no half-written directory


def test_pick_takes_the_fastest_mode_within_the_parity_gate() -> None:
    measured = [
        ModeMeasurement("fp32", 800.0, 0.0),
        ModeMeasurement("ort-int8", 300.0, 0.05),  # fastest, but fails the gate
        ModeMeasurement("ort-int8-vit", 450.0, 0.001),
        ModeMeasurement("bf16", None, None, "RuntimeError: no"),
    ]
    choice = pick(measured)
    assert choice.mode == "ort-int8-vit"
    assert "ort-int8 300 ms (fails parity, p99 |dT| 0.050)" in choice.reason and "fp32 800 ms" in choice.reason
    assert pick([ModeMeasurement("fp32", None, None, "x")]).mode == "fp32"


def test_auto_measures_once_then_reuses_the_figures(
    tiny_model_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    auto = ClipSegBackend(str(tiny_model_dir), precision="auto", cache_dir=tmp_path)
    modes = available_precisions()
    assert "ort-int8" in modes and auto.precision in modes
    assert auto.precision_reason.startswith("auto: fastest within the parity gate")
    for mode in modes:
        assert f"{mode} " in auto.precision_reason

    def no_measuring(*args: object, **kwargs: object) -> None:
        raise AssertionError("measured again")

    monkeypatch.setattr(precision_choice, "measure_modes", no_measuring)
    again = ClipSegBackend(str(tiny_model_dir), precision="auto", cache_dir=tmp_path)
    assert again.precision == auto.precision and again.precision_reason.endswith(", cached)")


def test_auto_survives_a_mode_that_cannot_be_built(
    tiny_model_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def broken(*args: object) -> None:
        raise RuntimeError("exporter exploded")

    monkeypatch.setattr(onnx_runtime, "_export", broken)
    auto = ClipSegBackend(str(tiny_model_dir), precision="auto", cache_dir=tmp_path)
    assert not auto.precision.startswith("ort-")
    [stored] = (tmp_path / "precision").glob("*.json")
    measured = {m["mode"]: ModeMeasurement(**m) for m in json.loads(stored.read_text())["measurements"]}
    assert measured["ort-int8"].ms_per_frame is None and "exporter exploded" in measured["ort-int8"].error
    assert measured["fp32"].passes and not measured["ort-fp32"].passes
