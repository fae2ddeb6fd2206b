from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import TINY_INPUT_SIZE, textured_image

torch = pytest.importorskip("torch")

from gcdtrav.service.backends import ModelUnavailableError, SegmentationBackend  # noqa: E402
from gcdtrav.service.backends.clipseg import ClipSegBackend  # noqa: E402

CONCEPTS = ["water", "mud", "grass", "gravel", "asphalt road"]


def assert_same_logits(fast: np.ndarray, reference: np.ndarray) -> None:
    """Equal up to float32 rounding, relative to the logits' scale (hundreds with random weights)."""
    assert fast.shape == reference.shape
    assert float(np.abs(fast - reference).max()) <= 1e-6 * float(np.abs(reference).max())


@pytest.mark.parametrize("shape", [(480, 640), (1, 1), (353, 17)])
def test_preprocessing_is_the_normalised_resize_channel_first(shape: tuple[int, int]) -> None:
    import cv2
    from gcdtrav.service.backends.clipseg import Preprocessing

    preprocess = Preprocessing(size=32, mean=(0.5, 0.25, 0.0), std=(0.5, 0.1, 2.0))
    image = np.random.default_rng(1).integers(0, 256, (*shape, 3), dtype=np.uint8)
    image[0, 0] = (0, 255, 128)  # both ends of the range, wherever the resize takes them
    pixels = preprocess(image)
    assert pixels.shape == (1, 3, 32, 32) and pixels.dtype == torch.float32 and pixels.is_contiguous()
    resized = cv2.resize(image, (32, 32), interpolation=cv2.INTER_LINEAR).astype(np.float64)
    expected = (resized / 255.0 - np.array(preprocess.mean)) / np.array(preprocess.std)
    np.testing.assert_allclose(pixels[0].numpy(), expected.transpose(2, 0, 1), rtol=0, atol=1e-6)


def test_loads_through_the_real_path_and_is_a_backend(tiny_backend: ClipSegBackend) -> None:
    assert isinstance(tiny_backend, SegmentationBackend)
    assert tiny_backend.preprocess.size == TINY_INPUT_SIZE  # read from preprocessor_config.json
    assert tiny_backend.extract_layers == [1, 2, 3]
    described = tiny_backend.describe()  # what the service reads of it
    assert described.input_size == (TINY_INPUT_SIZE, TINY_INPUT_SIZE) and described.model_id == tiny_backend.model_id
    assert (described.precision, described.precision_reason) == ("fp32", "asked for fp32")
    assert not described.measuring and not described.needs_measurement


def test_fast_path_matches_transformers_forward(tiny_backend: ClipSegBackend) -> None:
    for seed, (h, w) in enumerate([(120, 160), (96, 96), (301, 77)]):
        image = textured_image(h, w, seed)
        fast = tiny_backend.logits(image, tiny_backend.prepare(CONCEPTS))
        naive = tiny_backend.naive_logits(image, CONCEPTS)
        assert fast.shape == naive.shape == (len(CONCEPTS), TINY_INPUT_SIZE, TINY_INPUT_SIZE)
        assert fast.dtype == np.float32
        assert_same_logits(fast, naive)


def test_single_concept_batch(tiny_backend: ClipSegBackend) -> None:
    image = textured_image(64, 64)
    fast = tiny_backend.logits(image, tiny_backend.prepare(["water"]))
    assert_same_logits(fast, tiny_backend.naive_logits(image, ["water"]))


def test_vision_encoder_runs_once_and_stops_at_last_extracted_layer(tiny_backend: ClipSegBackend) -> None:
    layers = tiny_backend.model.clip.vision_model.encoder.layers
    calls = [0] * len(layers)
    hooks = [
        layer.layer_norm1.register_forward_hook(lambda *_, i=i: calls.__setitem__(i, calls[i] + 1))
        for i, layer in enumerate(layers)
    ]
    try:
        tiny_backend.logits(textured_image(80, 80), tiny_backend.prepare(CONCEPTS))
    finally:
        for hook in hooks:
            hook.remove()
    assert calls == [1, 1, 1, 1, 0]  # 5 layers, extract_layers [1, 2, 3]: layer 4 never runs


def test_text_embeddings_are_cached_per_anchor_set(tiny_backend: ClipSegBackend) -> None:
    text_model = tiny_backend.model.clip.text_model
    calls = []
    hook = text_model.register_forward_hook(lambda *_: calls.append(1))
    try:
        first = tiny_backend.prepare(["ice", "snow"])
        second = tiny_backend.prepare(["ice", "snow"])
        tiny_backend.prepare(["snow", "ice"])
    finally:
        hook.remove()
    assert first is second
    assert len(calls) == 2


def test_missing_directory_says_how_to_provide_weights(tmp_path: Path) -> None:
    with pytest.raises(ModelUnavailableError, match=r"does not exist.*--model"):
        ClipSegBackend(str(tmp_path / "nothing-here"))


def test_directory_without_weights(tmp_path: Path) -> None:
    (tmp_path / "config.json").write_text("{}")
    with pytest.raises(ModelUnavailableError, match="GCDTRAV_MODEL"):
        ClipSegBackend(str(tmp_path))


def test_unreachable_hub_id_is_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    with pytest.raises(
        ModelUnavailableError, match=r"'CIDAS/clipseg-rd64-refined' is not a local directory.*hf download"
    ):
        ClipSegBackend("CIDAS/clipseg-rd64-refined")


@pytest.mark.parametrize("precision", ["bf16", "bf16-vit", "int8"])
def test_fast_modes_keep_parity_with_fp32(tiny_model_dir: Path, tiny_backend: ClipSegBackend, precision: str) -> None:
    from gcdtrav.schemas.anchors import default_anchor_set
    from gcdtrav.service.backends.precision_choice import PARITY_P99_DT_LIMIT, parity
    from gcdtrav.service.commands.bench import activation_cosine

    fast = ClipSegBackend(str(tiny_model_dir), precision=precision)
    assert fast.precision == precision
    cas = default_anchor_set()
    image = textured_image(100, 120, seed=7)
    reference = tiny_backend.logits(image, tiny_backend.prepare(cas.concepts))
    candidate = fast.logits(image, fast.prepare(cas.concepts))
    report = parity(reference, candidate, cas)
    assert report["p99_dT"] <= PARITY_P99_DT_LIMIT
    assert report["max_dT"] < 0.1
    pixels = tiny_backend.preprocess(image)
    assert activation_cosine(tiny_backend.vision_activations(pixels), fast.vision_activations(pixels)) > 0.99
    # The fp32 model itself is untouched: transformers' forward still matches the fp32 fast path.
    assert_same_logits(reference, tiny_backend.naive_logits(image, cas.concepts))


def test_parity_measure_sees_errors_and_nothing_else(tiny_backend: ClipSegBackend) -> None:
    from gcdtrav.schemas.anchors import default_anchor_set
    from gcdtrav.service.backends.precision_choice import PARITY_P99_DT_LIMIT, parity

    cas = default_anchor_set()
    reference = tiny_backend.logits(textured_image(100, 120, seed=7), tiny_backend.prepare(cas.concepts))
    same = parity(reference, reference.copy(), cas)
    assert same["max_dT"] == 0 and same["top_anchor_changed"] == 0
    shifted = parity(reference, reference + 123.0, cas)  # a per-patch offset: the softmax ignores it
    assert shifted["max_dT"] < 1e-5
    noise = np.random.default_rng(0).normal(0, 0.05 * reference.std(), size=reference.shape).astype(np.float32)
    noisy = parity(reference, reference + noise, cas)  # 5 % anchor-dependent error: must fail the gate
    assert noisy["p99_dT"] > PARITY_P99_DT_LIMIT and noisy["top_anchor_changed"] > 0.05


def test_precision_is_validated(tiny_model_dir: Path) -> None:
    from gcdtrav.service.backends.clipseg import check_precision

    assert check_precision("ort-int8") == "ort-int8"
    with pytest.raises(ValueError, match="precision must be one of auto, fp32, bf16"):
        check_precision("fp8")
    with pytest.raises(ValueError, match="precision must be one of"):
        ClipSegBackend(str(tiny_model_dir), precision="fp8")


@pytest.mark.parametrize(("precision", "layers_left"), [("fp32", 4), ("bf16", 0)])
def test_service_backend_releases_the_vision_layers_it_does_not_run(
    tiny_model_dir: Path, tiny_backend: ClipSegBackend, precision: str, layers_left: int
) -> None:
    lean = ClipSegBackend(str(tiny_model_dir), precision=precision)  # as the service builds it
    assert not lean.keeps_reference
    # tiny model: 5 ViT layers, decoder reads 1..3; fp32 shares layers 0..3 with the trunk, bf16 copies them
    assert len(lean.model.clip.vision_model.encoder.layers) == layers_left
    with pytest.raises(RuntimeError, match="keep_reference=True"):
        lean.naive_logits(textured_image(64, 64), CONCEPTS)
    image = textured_image(100, 90, seed=11)
    reference = tiny_backend.logits(image, tiny_backend.prepare(CONCEPTS))
    logits = lean.logits(image, lean.prepare(CONCEPTS))
    if precision == "fp32":
        assert_same_logits(logits, reference)  # releasing changes nothing the fast path computes
    else:
        assert np.corrcoef(logits.ravel(), reference.ravel())[0, 1] > 0.999


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="Linux only")
def test_release_pages_frees_only_whole_pages_inside_the_tensor() -> None:
    import mmap

    from gcdtrav.service.backends.clipseg import release_pages

    block = torch.ones(8 * mmap.PAGESIZE // 4 + 123, dtype=torch.float32)  # malloc'd: not page aligned in general
    tensor = block[5:]  # a view: its storage is the whole block
    release_pages(tensor)
    values = block.numpy()
    start = block.untyped_storage().data_ptr()
    offsets = start + np.arange(values.size) * 4
    first = -(-start // mmap.PAGESIZE) * mmap.PAGESIZE
    last = (start + values.size * 4) // mmap.PAGESIZE * mmap.PAGESIZE
    inside = (offsets >= first) & (offsets + 4 <= last)
    assert inside.sum() >= 6 * mmap.PAGESIZE // 4  # most of it was released (anonymous memory reads as 0)
    assert (values[inside] == 0).all() and (values[~inside] == 1).all()
