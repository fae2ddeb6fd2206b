"""Count CLIP BPE tokens without torch or transformers.

The anchor-set schema must reject a concept that CLIP's 77-token text context would truncate, and the
schema lives in the torch-free base install. This is a compact re-implementation of the byte-level BPE
of OpenAI's CLIP (MIT) over the same vocabulary file (shipped in ``data/``); tests check it against
transformers' ``CLIPTokenizer``. Only the number of tokens is needed, so no ids are produced.
"""

from __future__ import annotations

import gzip
import re
import unicodedata
from functools import cache, lru_cache
from importlib import resources

CLIP_CONTEXT_LENGTH = 77
# <|startoftext|> and <|endoftext|> take two of the 77 positions.
MAX_CONCEPT_TOKENS = CLIP_CONTEXT_LENGTH - 2

# CLIP's pattern with \p{L} and \p{N} spelled for the standard `re` module.
_WORD_PATTERN = re.compile(
    r"<\|startoftext\|>|<\|endoftext\|>|'s|'t|'re|'ve|'m|'ll|'d|[^\W\d_]+|\d|(?:[^\s\w]|_)+",
    re.IGNORECASE,
)


@cache
def _byte_to_unicode() -> dict[int, str]:
    printable = (
        list(range(ord("!"), ord("~") + 1)) + list(range(ord("¡"), ord("¬") + 1)) + list(range(ord("®"), ord("ÿ") + 1))
    )
    codes = printable[:]
    extra = 0
    for byte in range(256):
        if byte not in printable:
            printable.append(byte)
            codes.append(256 + extra)
            extra += 1
    return dict(zip(printable, (chr(c) for c in codes), strict=True))


@cache
def _merge_ranks() -> dict[tuple[str, str], int]:
    data = resources.files("gcdtrav.schemas").joinpath("data/bpe_simple_vocab_16e6.txt.gz").read_bytes()
    lines = gzip.decompress(data).decode("utf-8").split("\n")
    # The first line is a header; CLIP uses the next 49152 - 256 - 2 merges.
    merges = lines[1 : 49152 - 256 - 2 + 1]
    return {tuple(line.split()): rank for rank, line in enumerate(merges)}  # type: ignore[misc]


@lru_cache(maxsize=4096)
def _bpe_piece_count(word: str) -> int:
    ranks = _merge_ranks()
    symbols = [*word[:-1], word[-1] + "</w>"]
    while len(symbols) > 1:
        pairs = {(symbols[i], symbols[i + 1]) for i in range(len(symbols) - 1)}
        best = min(pairs, key=lambda pair: ranks.get(pair, float("inf")))
        if best not in ranks:
            break
        merged: list[str] = []
        i = 0
        while i < len(symbols):
            if i < len(symbols) - 1 and (symbols[i], symbols[i + 1]) == best:
                merged.append(symbols[i] + symbols[i + 1])
                i += 2
            else:
                merged.append(symbols[i])
                i += 1
        symbols = merged
    return len(symbols)


def count_clip_tokens(text: str) -> int:
    """Number of BPE tokens CLIP's tokenizer makes of ``text`` (without start/end tokens)."""
    # Same normalisation as the Hugging Face CLIP tokenizer: NFC, whitespace folded, lower case.
    cleaned = re.sub(r"\s+", " ", unicodedata.normalize("NFC", text)).lower()
    table = _byte_to_unicode()
    total = 0
    for word in _WORD_PATTERN.findall(cleaned):
        total += _bpe_piece_count("".join(table[b] for b in word.encode("utf-8")))
    return total
