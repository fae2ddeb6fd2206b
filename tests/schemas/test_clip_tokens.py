from __future__ import annotations

from pathlib import Path

import pytest
from gcdtrav.schemas.clip_tokens import count_clip_tokens

SAMPLES = [
    "water",
    "cobblestone",
    "asphalt road",
    "a photo of wet, muddy gravel",
    "Tall GRASS   and\tweeds",
    "don't drive here",
    "route 66 exit 12b",
    "café crème",
    "snow-covered ice!!",
    "under_score & co.",
    "straße über feld",
    "42",
    " leading space",
    "x" * 120,
    "ünïcødé ░▒▓ symbols",
]


@pytest.mark.parametrize("text", SAMPLES)
def test_matches_transformers_clip_tokenizer(tiny_model_dir: Path, text: str) -> None:
    from transformers import CLIPTokenizer

    tokenizer = CLIPTokenizer.from_pretrained(tiny_model_dir)
    expected = len(tokenizer(text)["input_ids"]) - 2  # without start/end tokens
    assert count_clip_tokens(text) == expected


def test_counts_grow_with_text() -> None:
    assert count_clip_tokens("gravel") == 1
    assert count_clip_tokens("gravel " * 10) == 10
