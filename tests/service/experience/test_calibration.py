"""Every calibration figure recomputed from the pairs with plain numpy and math (docs/calibration.md)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from gcdtrav.schemas.anchors import Anchor, AnchorSet
from gcdtrav.service.experience.calibration import QUANTILE_TOLERANCE, calibration_figures

ANCHORS = AnchorSet(
    anchors=[
        Anchor(concept="water", position=0.05, width=0.0),
        Anchor(concept="bush", position=0.25, width=0.05),
        Anchor(concept="grass", position=0.7, width=0.1),
        Anchor(concept="asphalt", position=0.95, width=0.0),
    ]
)
TAU = 0.3


def phi(z: float) -> float:
    return 0.5 * (1 + math.erf(z / math.sqrt(2)))


def cdf_at_most(w: np.ndarray, t: float) -> float:
    return sum(
        wk * (phi((t - p) / s) if s > 0 else float(p <= t))
        for wk, p, s in zip(w, ANCHORS.positions, ANCHORS.widths, strict=True)
    )


def p_below(w: np.ndarray, tau: float) -> float:
    return sum(
        wk * (phi((tau - p) / s) if s > 0 else float(p < tau))
        for wk, p, s in zip(w, ANCHORS.positions, ANCHORS.widths, strict=True)
    )


def lower_quantile(w: np.ndarray, alpha: float) -> float:
    low, high = -2.0, 3.0
    for _ in range(200):
        mid = (low + high) / 2
        low, high = (low, mid) if cdf_at_most(w, mid) >= alpha else (mid, high)
    return high


def ranks(values: np.ndarray) -> np.ndarray:
    out = np.empty(len(values))
    out[np.argsort(values)] = np.arange(1, len(values) + 1)
    return out


def sparsification(error: np.ndarray, order_by: np.ndarray, steps: int = 50) -> np.ndarray:
    order = np.argsort(-order_by, kind="stable")
    sorted_error = np.abs(error)[order]
    return np.array([sorted_error[int(np.floor(f * len(error))) :].mean() for f in np.arange(steps) / steps])


def pairs(count: int, seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    weights = rng.dirichlet(np.full(len(ANCHORS), 0.5), size=count)
    outcomes = np.clip(weights @ np.array(ANCHORS.positions) + rng.normal(0, 0.15, count), 0, 1)
    return weights, outcomes


def test_every_figure_recomputed_with_plain_numpy() -> None:
    weights, y = pairs(400)
    figures = calibration_figures(weights, y, ANCHORS, TAU)
    positions, widths = np.array(ANCHORS.positions), np.array(ANCHORS.widths)
    t = weights @ positions
    u = np.sqrt(weights @ (positions**2 + widths**2) - t**2)
    error = t - y
    assert figures.pairs == 400
    assert figures.mae == pytest.approx(np.abs(error).mean(), abs=1e-6)
    assert figures.bias == pytest.approx(error.mean(), abs=1e-6)
    for alpha in (0.05, 0.1, 0.2):
        q = np.array([lower_quantile(w, alpha) for w in weights])
        expected = np.mean(y >= q - QUANTILE_TOLERANCE)
        assert figures.coverage[f"{alpha:g}"] == pytest.approx(expected, abs=1 / 400 + 1e-9)
    predicted = np.array([p_below(w, TAU) for w in weights])
    index = np.minimum((predicted * 10).astype(int), 9)
    ece = 0.0
    for b, row in enumerate(figures.reliability):
        members = index == b
        assert row.count == members.sum()
        if members.any():
            assert row.predicted == pytest.approx(predicted[members].mean(), abs=1e-5)
            assert row.observed == pytest.approx(np.mean(y[members] < TAU))
            ece += members.mean() * abs(np.mean(y[members] < TAU) - predicted[members].mean())
    assert figures.ece == pytest.approx(ece, abs=1e-5)
    fractions = np.arange(50) / 50
    gap = sparsification(error, u) - sparsification(error, np.abs(error))
    assert figures.ause == pytest.approx(float(np.sum((gap[1:] + gap[:-1]) / 2 * np.diff(fractions))), abs=1e-4)
    rho = np.corrcoef(ranks(u), ranks(np.abs(error)))[0, 1]
    assert figures.spearman_u_error == pytest.approx(rho, abs=1e-3)
    dominant = weights.argmax(axis=1)
    for k, anchor in enumerate(figures.anchors):
        assert anchor.concept == ANCHORS.concepts[k]
        assert anchor.weight_mass == pytest.approx(weights[:, k].sum(), rel=1e-6)
        assert anchor.dominant_pairs == (dominant == k).sum()
        assert anchor.dominant_mean_outcome == pytest.approx(y[dominant == k].mean())


def test_a_calibrated_mixture_covers_its_quantiles() -> None:
    """Outcomes drawn from each pair's own mixture (Gaussian anchors: a point mass's atom would cover more than
    1 - alpha, by definition): coverage of q_alpha is 1 - alpha, P(T < tau) reliable."""
    anchors = AnchorSet(default_width=0.06, anchors=[a.model_copy(update={"width": None}) for a in ANCHORS.anchors])
    rng = np.random.default_rng(0)
    count = 20_000
    weights = rng.dirichlet(np.full(len(anchors), 0.7), size=count)
    anchor = np.array([rng.choice(len(anchors), p=w) for w in weights])
    y = rng.normal(np.array(anchors.positions)[anchor], np.array(anchors.widths)[anchor])
    figures = calibration_figures(weights, y, anchors, TAU)
    for alpha in (0.05, 0.1, 0.2):
        assert figures.coverage[f"{alpha:g}"] == pytest.approx(1 - alpha, abs=0.01)
    assert figures.ece is not None and figures.ece < 0.02
    assert figures.bias == pytest.approx(0.0, abs=0.01)


def test_one_outcome() -> None:
    figures = calibration_figures(np.array([[0.0, 0.0, 1.0, 0.0]]), np.array([0.6]), ANCHORS, TAU)
    assert figures.pairs == 1
    assert figures.mae == pytest.approx(0.1) and figures.bias == pytest.approx(0.1)
    assert figures.spearman_u_error is None  # a rank correlation of one pair is undefined
    assert figures.coverage["0.1"] == 1.0  # q_0.1 of N(0.7, 0.1) is 0.572 <= 0.6
    assert sum(row.count for row in figures.reliability) == 1
    assert figures.anchors[2].dominant_pairs == 1 and figures.anchors[2].dominant_mean_outcome == pytest.approx(0.6)
    assert figures.anchors[0].dominant_mean_outcome is None


def test_zero_outcomes() -> None:
    figures = calibration_figures(np.zeros((0, len(ANCHORS))), np.zeros(0), ANCHORS, TAU)
    assert figures.pairs == 0
    assert figures.mae is None and figures.bias is None and figures.ece is None and figures.ause is None
    assert set(figures.coverage.values()) == {None}
    assert all(row.count == 0 and row.predicted is None for row in figures.reliability)
    assert all(a.weight_mass == 0 and a.dominant_pairs == 0 for a in figures.anchors)
    assert figures.model_dump_json()  # None, never NaN, on the wire


def test_mismatched_lengths_are_refused() -> None:
    with pytest.raises(ValueError, match="2 weight rows for 3 outcomes"):
        calibration_figures(np.full((2, 4), 0.25), np.zeros(3), ANCHORS, TAU)


def test_the_reliability_diagram_is_a_png(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    from gcdtrav.client.commands.calibration_plot import reliability_diagram

    weights, y = pairs(200)
    for name, figures in (
        ("some.png", calibration_figures(weights, y, ANCHORS, TAU)),
        ("none.png", calibration_figures(np.zeros((0, 4)), np.zeros(0), ANCHORS, TAU)),
    ):
        reliability_diagram(figures, tmp_path / name, "cam")
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
