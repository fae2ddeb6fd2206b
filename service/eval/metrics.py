"""Error and uncertainty-quality metrics on flat arrays of sampled pixels (numpy only)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

ERROR_THRESHOLD = 0.25  # |error| above this is a "wrong" pixel for the AUROC of U
SPARSIFICATION_STEPS = 50


def mae(error: NDArray[np.floating]) -> float:
    return float(np.mean(np.abs(error))) if error.size else float("nan")


def rmse(error: NDArray[np.floating]) -> float:
    return float(np.sqrt(np.mean(np.square(error)))) if error.size else float("nan")


def average_ranks(values: NDArray[np.floating]) -> NDArray[np.float64]:
    """Ranks 1..n, ties sharing their average rank (as scipy.stats.rankdata)."""
    order = np.argsort(values, kind="mergesort")
    sorted_values = values[order]
    ranks = np.empty(len(values), dtype=np.float64)
    boundaries = np.flatnonzero(np.diff(sorted_values)) + 1
    starts = np.concatenate([[0], boundaries])
    ends = np.concatenate([boundaries, [len(values)]])
    ranks[order] = np.repeat((starts + ends + 1) / 2.0, ends - starts)  # each tie group its average rank
    return ranks


def spearman(a: NDArray[np.floating], b: NDArray[np.floating]) -> float:
    """Spearman's rank correlation; NaN when either side is constant."""
    if len(a) < 2:
        return float("nan")
    ra, rb = average_ranks(np.asarray(a)), average_ranks(np.asarray(b))
    if ra.std() == 0 or rb.std() == 0:
        return float("nan")
    return float(np.corrcoef(ra, rb)[0, 1])


def auroc(scores: NDArray[np.floating], positive: NDArray[np.bool_]) -> float:
    """Area under the ROC curve of ``scores`` for ``positive`` (Mann-Whitney, ties count half)."""
    n_pos = int(positive.sum())
    n_neg = len(positive) - n_pos
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    ranks = average_ranks(np.asarray(scores))
    return float((ranks[positive].sum() - n_pos * (n_pos + 1) / 2) / (n_pos * n_neg))


def sparsification_curve(
    error: NDArray[np.floating], order_by: NDArray[np.floating], steps: int = SPARSIFICATION_STEPS
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """MAE of the pixels left after removing the fraction f with the highest ``order_by``, f in [0, 1)."""
    abs_error = np.abs(np.asarray(error, dtype=np.float64))
    order = np.argsort(-np.asarray(order_by), kind="stable")
    remaining = abs_error[order][::-1].cumsum()[::-1]  # sum of errors from index i to the end
    count = len(abs_error)
    fractions = np.arange(steps) / steps
    start = np.floor(fractions * count).astype(int)
    curve = remaining[start] / (count - start)
    return fractions, curve


def ause(error: NDArray[np.floating], uncertainty: NDArray[np.floating]) -> dict[str, float]:
    """Area Under the Sparsification Error: the gap between removing pixels by uncertainty and by the
    true error (the oracle), integrated over the removed fraction. 0 = U ranks errors perfectly.

    ``ause`` is in MAE units; ``ause_relative`` divides both curves by the MAE before removal.
    """
    if len(error) == 0:
        return {"ause": float("nan"), "ause_relative": float("nan")}
    fractions, by_u = sparsification_curve(error, uncertainty)
    _, oracle = sparsification_curve(error, np.abs(error))
    gap = by_u - oracle
    area = float(np.trapezoid(gap, fractions))
    first = by_u[0]
    return {"ause": area, "ause_relative": area / first if first > 0 else float("nan")}


def summary(error: NDArray[np.floating], uncertainty: NDArray[np.floating]) -> dict[str, float]:
    wrong = np.abs(error) > ERROR_THRESHOLD
    return {
        "pixels": float(len(error)),
        "mae": mae(error),
        "rmse": rmse(error),
        "spearman_u_abs_error": spearman(uncertainty, np.abs(error)),
        f"auroc_u_error_gt_{ERROR_THRESHOLD}": auroc(uncertainty, wrong),
        "fraction_error_gt_threshold": float(wrong.mean()) if len(error) else float("nan"),
        **ause(error, uncertainty),
    }
