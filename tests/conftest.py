"""Shared fixtures: a tiny random-weight CLIPSeg saved in the Hugging Face layout, built offline."""

from __future__ import annotations

import gzip
import json
import os
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

# Nothing in the test suite may reach a model hub.
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")

TINY_INPUT_SIZE = 96  # != the vision config's 64, so position-embedding interpolation is exercised


def clip_vocab_and_merges() -> tuple[dict[str, int], list[str]]:
    """CLIP's real vocabulary, built from the BPE merges file shipped in gcdtrav.schemas."""
    from gcdtrav.schemas.clip_tokens import _byte_to_unicode

    raw = resources.files("gcdtrav.schemas").joinpath("data/bpe_simple_vocab_16e6.txt.gz").read_bytes()
    merges = gzip.decompress(raw).decode("utf-8").split("\n")[1 : 49152 - 256 - 2 + 1]
    symbols = list(_byte_to_unicode().values())
    vocab_list = symbols + [s + "</w>" for s in symbols] + ["".join(m.split()) for m in merges]
    vocab_list += ["<|startoftext|>", "<|endoftext|>"]
    return {token: index for index, token in enumerate(vocab_list)}, merges


def build_tiny_clipseg(directory: Path, seed: int = 0) -> Path:
    import torch
    from transformers import CLIPSegConfig, CLIPSegForImageSegmentation, CLIPTokenizer

    torch.manual_seed(seed)
    config = CLIPSegConfig(
        text_config={
            "vocab_size": 49408,
            "hidden_size": 32,
            "intermediate_size": 64,
            "num_hidden_layers": 2,
            "num_attention_heads": 2,
            "max_position_embeddings": 77,
        },
        vision_config={
            "hidden_size": 32,
            "intermediate_size": 64,
            "num_hidden_layers": 5,
            "num_attention_heads": 2,
            "image_size": 64,
            "patch_size": 16,
        },
        projection_dim=16,
        extract_layers=[1, 2, 3],
        reduce_dim=16,
        decoder_num_attention_heads=2,
        decoder_intermediate_size=32,
        use_complex_transposed_convolution=True,
    )
    model = CLIPSegForImageSegmentation(config).eval()
    model.save_pretrained(directory)
    vocab, merges = clip_vocab_and_merges()
    # The slow-tokenizer files of the real checkpoint; transformers builds its tokenizer from them.
    (directory / "vocab.json").write_text(json.dumps(vocab), "utf-8")
    (directory / "merges.txt").write_text("#version: 0.2\n" + "\n".join(merges) + "\n", "utf-8")
    (directory / "tokenizer_config.json").write_text(
        json.dumps({"tokenizer_class": "CLIPTokenizer", "model_max_length": 77}), "utf-8"
    )
    CLIPTokenizer.from_pretrained(directory)  # fail here, not in the test, if the files are unusable
    (directory / "preprocessor_config.json").write_text(
        json.dumps(
            {
                "do_resize": True,
                "size": {"height": TINY_INPUT_SIZE, "width": TINY_INPUT_SIZE},
                "image_mean": [0.485, 0.456, 0.406],
                "image_std": [0.229, 0.224, 0.225],
            }
        )
    )
    return directory


@pytest.fixture(scope="session")
def tiny_model_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    pytest.importorskip("torch")
    return build_tiny_clipseg(tmp_path_factory.mktemp("tiny-clipseg"))


@pytest.fixture(scope="session")
def tiny_backend(tiny_model_dir: Path):  # type: ignore[no-untyped-def]
    from gcdtrav.service.backends.clipseg import ClipSegBackend

    return ClipSegBackend(str(tiny_model_dir))


@pytest.fixture()
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


def textured_image(height: int, width: int, seed: int = 0) -> np.ndarray:
    """A deterministic RGB image with structure (so logits vary across patches)."""
    generator = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width]
    base = np.stack([x * 255 // max(width - 1, 1), y * 255 // max(height - 1, 1), (x + y) % 256], axis=2)
    noise = generator.integers(0, 40, size=(height, width, 3))
    return np.clip(base + noise, 0, 255).astype(np.uint8)
