"""Calibration figures: how well an anchor set's T, U, quantiles and P(T < tau) predicted the outcomes the
robot met (docs/calibration.md defines each). Pure numpy on (pairs, anchors) weights; the risk measures come
from engine/risk.py, so a figure grades exactly what the service serves."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.experience import CALIBRATION_ALPHAS, AnchorFigures, CalibrationFigures, ReliabilityBin
from gcdtrav.service.engine import gcd, risk
from gcdtrav.service.eval import metrics
from numpy.typing import NDArray

RELIABILITY_BINS = 10
# q_alpha is float32 (engine/risk.py): an outcome equal to an anchor's position in float64 counts as reaching it.
QUANTILE_TOLERANCE = 1e-6


def alpha_key(alpha: float) -> str:
    return f"{alpha:g}"


def _number(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def calibration_figures(
    weights: NDArray[np.floating],
    outcomes: NDArray[np.floating],
    anchors: AnchorSet,
    tau: float,
    alphas: Sequence[float] = CALIBRATION_ALPHAS,
    bins: int = RELIABILITY_BINS,
) -> CalibrationFigures:
    """The figures of ``anchors`` over pairs: ``weights`` (m, n) in the set's concept order, ``outcomes`` (m,).
    Every figure but AUSE and Spearman's rho is a sum over pairs (``pair_sums``): the store keeps those sums as
    pairs arrive, and ``figures_from_sums`` is the one place they become figures."""
    w = np.asarray(weights, np.float64).reshape(-1, len(anchors))
    y = np.asarray(outcomes, np.float64).reshape(-1)
    if len(w) != len(y):
        raise ValueError(f"{len(w)} weight rows for {len(y)} outcomes")
    ause, spearman = ranked_figures(w, y, anchors)
    sums = pair_sums(w, y, anchors, tau, alphas, bins).sum(axis=0)
    return figures_from_sums(sums, anchors, tau, ause, spearman, alphas, bins)


def sums_length(concepts: int, alphas: int = len(CALIBRATION_ALPHAS), bins: int = RELIABILITY_BINS) -> int:
    """count, sum of T - y, sum of |T - y|, coverage counts per alpha, per reliability bin (count, predicted,
    observed), per anchor (weight mass, dominant pairs, their outcomes)."""
    return 3 + alphas + 3 * bins + 3 * concepts


def pair_sums(
    weights: NDArray[np.float64],
    outcomes: NDArray[np.float64],
    anchors: AnchorSet,
    tau: float,
    alphas: Sequence[float] = CALIBRATION_ALPHAS,
    bins: int = RELIABILITY_BINS,
) -> NDArray[np.float64]:
    """Each pair's addends of the figures (m, sums_length): summed over any set of pairs, they give its figures."""
    w, y = np.asarray(weights, np.float64), np.asarray(outcomes, np.float64)
    m, n = w.shape
    out = np.zeros((m, sums_length(n, len(alphas), bins)))
    if m == 0:
        return out
    positions, widths = np.asarray(anchors.positions), np.asarray(anchors.widths)
    by_anchor = w.T  # the engine's layout: anchors on axis 0
    t, _ = (values.astype(np.float64) for values in gcd.mixture_mean_std(by_anchor, positions, widths))
    out[:, 0], out[:, 1], out[:, 2] = 1.0, t - y, np.abs(t - y)
    for k, alpha in enumerate(alphas):
        out[:, 3 + k] = y >= risk.quantile(by_anchor, positions, widths, alpha) - QUANTILE_TOLERANCE
    below = risk.p_below(by_anchor, positions, widths, tau).astype(np.float64)
    index = np.clip(np.floor(below * bins).astype(int), 0, bins - 1)
    at = 3 + len(alphas)
    rows = np.arange(m)
    out[rows, at + index] = 1.0
    out[rows, at + bins + index] = below
    out[rows, at + 2 * bins + index] = y < tau
    at += 3 * bins
    out[:, at : at + n] = w
    dominant = np.argmax(w, axis=1)
    out[rows, at + n + dominant] = 1.0
    out[rows, at + 2 * n + dominant] = y
    return out


def figures_from_sums(
    sums: NDArray[np.float64],
    anchors: AnchorSet,
    tau: float,
    ause: float | None = None,
    spearman: float | None = None,
    alphas: Sequence[float] = CALIBRATION_ALPHAS,
    bins: int = RELIABILITY_BINS,
) -> CalibrationFigures:
    """The figures of summed ``pair_sums`` (weighted sums too: a robot's pairs may count less, sharing.py)."""
    count, n = float(sums[0]), len(anchors)
    if count <= 0:
        return _empty(anchors, tau, alphas, bins)
    at = 3 + len(alphas)
    counts, predicted, observed = (sums[at + k * bins : at + (k + 1) * bins] for k in range(3))
    reliability, ece = [], 0.0
    for b in range(bins):
        filled = counts[b] > 0
        mean_predicted = float(predicted[b] / counts[b]) if filled else None
        seen = float(observed[b] / counts[b]) if filled else None
        if mean_predicted is not None and seen is not None:
            ece += counts[b] / count * abs(seen - mean_predicted)
        reliability.append(ReliabilityBin(low=b / bins, high=(b + 1) / bins, count=round(float(counts[b])),
                                          predicted=mean_predicted, observed=seen))  # fmt: skip
    at += 3 * bins
    mass, dominant, dominant_outcomes = (sums[at + k * n : at + (k + 1) * n] for k in range(3))
    return CalibrationFigures(
        pairs=round(count),
        mae=float(sums[2] / count),
        bias=float(sums[1] / count),
        coverage={alpha_key(alpha): float(sums[3 + k] / count) for k, alpha in enumerate(alphas)},
        tau=tau,
        reliability=reliability,
        ece=float(ece),
        ause=ause,
        spearman_u_error=spearman,
        anchors=[
            AnchorFigures(
                concept=concept,
                position=position,
                width=width,
                weight_mass=float(mass[k]),
                dominant_pairs=round(float(dominant[k])),
                dominant_mean_outcome=float(dominant_outcomes[k] / dominant[k]) if dominant[k] > 0 else None,
            )
            for k, (concept, position, width) in enumerate(
                zip(anchors.concepts, anchors.positions, anchors.widths, strict=True)
            )
        ],
    )


def ranked_figures(
    weights: NDArray[np.float64], outcomes: NDArray[np.float64], anchors: AnchorSet
) -> tuple[float | None, float | None]:
    """AUSE and Spearman's rho of U against |T - outcome|: they rank every pair, so no sum keeps them."""
    if len(outcomes) == 0:
        return None, None
    positions, widths = np.asarray(anchors.positions), np.asarray(anchors.widths)
    t, u = (v.astype(np.float64) for v in gcd.mixture_mean_std(weights.T, positions, widths))
    error = t - outcomes
    return _number(metrics.ause(error, u)["ause"]), _number(metrics.spearman(u, np.abs(error)))


def _empty(anchors: AnchorSet, tau: float, alphas: Sequence[float], bins: int) -> CalibrationFigures:
    return CalibrationFigures(
        pairs=0,
        mae=None,
        bias=None,
        coverage={alpha_key(alpha): None for alpha in alphas},
        tau=tau,
        reliability=[
            ReliabilityBin(low=b / bins, high=(b + 1) / bins, count=0, predicted=None, observed=None)
            for b in range(bins)
        ],
        ece=None,
        ause=None,
        spearman_u_error=None,
        anchors=[
            AnchorFigures(concept=c, position=p, width=w, weight_mass=0.0, dominant_pairs=0, dominant_mean_outcome=None)
            for c, p, w in zip(anchors.concepts, anchors.positions, anchors.widths, strict=True)
        ],
    )
