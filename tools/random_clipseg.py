"""Random-weight CLIPSeg checkpoints in the Hugging Face layout, built offline.

Real weights can't always be downloaded (CI, air-gapped boxes). Tests use a tiny model; benchmarks use
the real rd64-refined architecture, whose compute cost is the real one. The tokenizer is CLIP's real
BPE vocabulary, shipped in ``gcdtrav.schemas``. Outputs of these models are meaningless: never ship them.
"""

from __future__ import annotations

import gzip
import json
import sys
from importlib import resources
from pathlib import Path
from typing import Any

from gcdtrav.schemas.clip_tokens import _byte_to_unicode

# CIDAS/clipseg-rd64-refined: CLIP ViT-B/16 + text transformer, rd64 decoder reading layers 3, 6, 9.
REFINED_RD64: dict[str, Any] = {
    "text_config": {"hidden_size": 512, "intermediate_size": 2048, "num_attention_heads": 8, "num_hidden_layers": 12},
    "vision_config": {
        "hidden_size": 768,
        "intermediate_size": 3072,
        "num_attention_heads": 12,
        "num_hidden_layers": 12,
        "image_size": 224,
        "patch_size": 16,
    },
    "projection_dim": 512,
    "extract_layers": [3, 6, 9],
    "reduce_dim": 64,
    "decoder_num_attention_heads": 4,
    "decoder_intermediate_size": 2048,
    "use_complex_transposed_convolution": True,
}
TINY: dict[str, Any] = {
    "text_config": {"hidden_size": 32, "intermediate_size": 64, "num_attention_heads": 2, "num_hidden_layers": 2},
    "vision_config": {
        "hidden_size": 32,
        "intermediate_size": 64,
        "num_attention_heads": 2,
        "num_hidden_layers": 5,
        "image_size": 64,
        "patch_size": 16,
    },
    "projection_dim": 16,
    "extract_layers": [1, 2, 3],
    "reduce_dim": 16,
    "decoder_num_attention_heads": 2,
    "decoder_intermediate_size": 32,
    "use_complex_transposed_convolution": True,
}
PRESETS = {"rd64-refined": REFINED_RD64, "tiny": TINY}


def clip_vocab_and_merges() -> tuple[dict[str, int], list[str]]:
    """CLIP's vocabulary (byte symbols, the same with </w>, one token per merge, two specials)."""
    raw = resources.files("gcdtrav.schemas").joinpath("data/bpe_simple_vocab_16e6.txt.gz").read_bytes()
    merges = gzip.decompress(raw).decode("utf-8").split("\n")[1 : 49152 - 256 - 2 + 1]
    symbols = list(_byte_to_unicode().values())
    tokens = symbols + [s + "</w>" for s in symbols] + ["".join(m.split()) for m in merges]
    tokens += ["<|startoftext|>", "<|endoftext|>"]
    return {token: index for index, token in enumerate(tokens)}, merges


def write_clip_tokenizer(directory: Path) -> None:
    """The slow-tokenizer files of the real checkpoint; transformers' CLIPTokenizer reads them."""
    vocab, merges = clip_vocab_and_merges()
    (directory / "vocab.json").write_text(json.dumps(vocab), "utf-8")
    (directory / "merges.txt").write_text("#version: 0.2\n" + "\n".join(merges) + "\n", "utf-8")
    (directory / "tokenizer_config.json").write_text(
        json.dumps({"tokenizer_class": "CLIPTokenizer", "model_max_length": 77}), "utf-8"
    )


def checkpoint_or_random(model: str | Path | None, scratch: Path) -> Path:
    """``model`` if given, else random weights of the real rd64-refined architecture written under ``scratch``:
    what the benchmarks time when no checkpoint is at hand (the compute is the real one)."""
    if model is not None:
        return Path(model)
    print("building random weights of the real architecture (CLIPSeg rd64-refined) ...", file=sys.stderr)
    return save_random_clipseg(scratch / "model", preset="rd64-refined")


def benchmark_model(model: str | Path | None, quick: bool, scratch: Path) -> str:
    """The checkpoint a benchmark runs: ``model`` if given; ``quick``: a tiny random model (correctness only);
    else random weights of the real architecture."""
    if model is None and quick:
        return str(save_random_clipseg(scratch / "tiny", preset="tiny", input_size=96))
    return str(checkpoint_or_random(model, scratch))


def save_random_clipseg(directory: Path, preset: str = "tiny", input_size: int = 352, seed: int = 0) -> Path:
    """Write config, random weights, tokenizer and preprocessor files to ``directory``."""
    import torch
    from transformers import CLIPSegConfig, CLIPSegForImageSegmentation

    directory.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(seed)
    model = CLIPSegForImageSegmentation(CLIPSegConfig(**PRESETS[preset])).eval()
    model.save_pretrained(directory)
    write_clip_tokenizer(directory)
    (directory / "preprocessor_config.json").write_text(
        json.dumps(
            {
                "do_resize": True,
                "size": {"height": input_size, "width": input_size},
                "image_mean": [0.485, 0.456, 0.406],
                "image_std": [0.229, 0.224, 0.225],
            }
        ),
        "utf-8",
    )
    return directory
