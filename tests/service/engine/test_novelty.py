from __future__ import annotations

import numpy as np
import pytest
from gcdtrav.service.engine.novelty import match_score


def test_is_the_sigmoid_of_the_best_logit() -> None:
    logits = np.array([[-3.0, 2.0], [1.0, -5.0], [0.0, 0.5]], np.float32)
    np.testing.assert_allclose(match_score(logits), 1 / (1 + np.exp(-np.array([1.0, 2.0]))), rtol=1e-6)


def test_monotone_in_the_best_logit_and_inside_zero_one() -> None:
    best = np.linspace(-15.0, 15.0, 301, dtype=np.float32)
    logits = np.stack([best, best - 1.0, np.full_like(best, -20.0)])
    scores = match_score(logits)
    assert (np.diff(scores) >= 0).all()
    assert (np.diff(scores[best < 8]) > 0).all()  # above, float32's steps near 1 are coarser than the sigmoid's
    assert ((scores > 0) & (scores < 1)).all()
    assert match_score(np.array([[-1e4], [1e4]], np.float32))[0] == 1.0
    assert match_score(np.array([[-1e4], [-1e3]], np.float32))[0] == 0.0


@pytest.mark.parametrize("patch_shape", [(), (5,), (4, 6)])
def test_shapes(patch_shape: tuple[int, ...]) -> None:
    scores = match_score(np.random.default_rng(0).normal(0, 3, (13, *patch_shape)))
    assert scores.shape == patch_shape and scores.dtype == np.float32


def test_logits_without_anchors_are_refused() -> None:
    with pytest.raises(ValueError, match="anchors on axis 0"):
        match_score(np.zeros((0, 4)))
