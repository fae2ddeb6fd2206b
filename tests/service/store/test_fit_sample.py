"""The fitting sample (issue 57): per (tuple, source) a uniform reservoir of the whole history, kept after the
raw pairs go, on SQLite and PostgreSQL alike."""

from __future__ import annotations

import numpy as np
from gcdtrav.service.store import Store
from store_test_helpers import pair

GRASS = ("grass", "gravel", "rock")


def test_the_sample_is_uniform_over_the_whole_history_though_the_bounds_keep_the_last_pairs(store: Store) -> None:
    """10,000 pairs of r1 appended in batches, 600 kept raw; the 400-pair sample spans all 10,000: its stamps
    fall evenly in ten slices of the history (a chi-square test; 27.9 is the 0.1 % point for 9 degrees)."""
    for start in range(0, 10_000, 500):
        batch = [pair(GRASS, k, source="r1") for k in range(start, start + 500)]
        store.append_pairs(batch, max_pairs=600, max_bytes=10**9, sample_size=400)
    store.append_pairs([pair(GRASS, k, source="r2") for k in range(50)], 10**6, 10**9, sample_size=400)
    assert store.totals().pairs == 650
    sample = store.sample(["rock", "grass", "gravel"])
    sources = np.asarray(sample.sources)
    assert (sources == "r1").sum() == 400 and (sources == "r2").sum() == 50  # a source under the size: all of it
    stamps = sample.stamps[sources == "r1"] - 1000.0  # pair k has stamp 1000 + k
    assert stamps.min() < 1_000 and stamps.max() > 9_000  # not only the last minutes
    counts = np.histogram(stamps, bins=10, range=(0, 10_000))[0]
    chi_square = float(((counts - 40) ** 2 / 40).sum())
    assert chi_square < 27.9, counts
    assert list(sample.stamps) == sorted(sample.stamps)


def test_without_a_size_nothing_is_sampled(store: Store) -> None:
    store.append_pairs([pair(GRASS, k) for k in range(5)], 100, 10**6)
    assert len(store.sample(GRASS)) == 0 and len(store.sample(("never", "seen"))) == 0
