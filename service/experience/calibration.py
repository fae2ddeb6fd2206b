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
    """The figures of ``anchors`` over pairs: ``weights`` (m, n) in the set's concept order, ``outcomes`` (m,)."""
    w = np.asarray(weights, np.float64).reshape(-1, len(anchors))
    y = np.asarray(outcomes, np.float64).reshape(-1)
    if len(w) != len(y):
        raise ValueError(f"{len(w)} weight rows for {len(y)} outcomes")
    positions, widths = np.asarray(anchors.positions), np.asarray(anchors.widths)
    by_anchor = w.T  # the engine's layout: anchors on axis 0
    count = len(y)
    if count == 0:
        return _empty(anchors, tau, alphas, bins)
    t, u = (values.astype(np.float64) for values in gcd.mixture_mean_std(by_anchor, positions, widths))
    error = t - y
    coverage: dict[str, float | None] = {
        alpha_key(alpha): float(np.mean(y >= risk.quantile(by_anchor, positions, widths, alpha) - QUANTILE_TOLERANCE))
        for alpha in alphas
    }
    below = risk.p_below(by_anchor, positions, widths, tau).astype(np.float64)
    reliability, ece = reliability_bins(below, y < tau, bins)
    return CalibrationFigures(
        pairs=count,
        mae=float(np.mean(np.abs(error))),
        bias=float(np.mean(error)),
        coverage=coverage,
        tau=tau,
        reliability=reliability,
        ece=ece,
        ause=_number(metrics.ause(error, u)["ause"]),
        spearman_u_error=_number(metrics.spearman(u, np.abs(error))),
        anchors=anchor_figures(w, y, anchors),
    )


def reliability_bins(
    predicted: NDArray[np.float64], happened: NDArray[np.bool_], bins: int
) -> tuple[list[ReliabilityBin], float | None]:
    """Equal-width bins of the predicted probability; ECE = sum over bins of share x |observed - predicted|."""
    index = np.clip(np.floor(predicted * bins).astype(int), 0, bins - 1)
    result, ece = [], 0.0
    for b in range(bins):
        members = index == b
        n = int(members.sum())
        mean_predicted = float(predicted[members].mean()) if n else None
        observed = float(happened[members].mean()) if n else None
        if mean_predicted is not None and observed is not None:
            ece += n / len(predicted) * abs(observed - mean_predicted)
        result.append(
            ReliabilityBin(low=b / bins, high=(b + 1) / bins, count=n, predicted=mean_predicted, observed=observed)
        )
    return result, (ece if len(predicted) else None)


def anchor_figures(
    weights: NDArray[np.float64], outcomes: NDArray[np.float64], anchors: AnchorSet
) -> list[AnchorFigures]:
    mass = weights.sum(axis=0) if len(weights) else np.zeros(len(anchors))
    dominant = np.argmax(weights, axis=1) if len(weights) else np.zeros(0, int)
    figures = []
    for k, (concept, position, width) in enumerate(
        zip(anchors.concepts, anchors.positions, anchors.widths, strict=True)
    ):
        where = dominant == k
        n = int(where.sum())
        figures.append(
            AnchorFigures(
                concept=concept,
                position=position,
                width=width,
                weight_mass=float(mass[k]),
                dominant_pairs=n,
                dominant_mean_outcome=float(outcomes[where].mean()) if n else None,
            )
        )
    return figures


def _empty(anchors: AnchorSet, tau: float, alphas: Sequence[float], bins: int) -> CalibrationFigures:
    reliability, _ = reliability_bins(np.zeros(0), np.zeros(0, bool), bins)
    return CalibrationFigures(
        pairs=0,
        mae=None,
        bias=None,
        coverage={alpha_key(alpha): None for alpha in alphas},
        tau=tau,
        reliability=reliability,
        ece=None,
        ause=None,
        spearman_u_error=None,
        anchors=anchor_figures(np.zeros((0, len(anchors))), np.zeros(0), anchors),
    )
