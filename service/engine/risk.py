"""Risk measures of the Gaussian Context Distribution, exact and vectorised over every patch.

Inputs as in gcd.py: weights with the anchors on axis 0 and any patch layout after it, anchor positions
mu_k and widths sigma_k (sigma_k = 0 is a point mass at mu_k). Per patch, with T ~ sum_k w_k N(mu_k, sigma_k^2):

  p_below   F(tau) = P(T < tau) = sum_k w_k Phi((tau - mu_k) / sigma_k)    point mass: 1 if mu_k < tau, else 0
  quantile  q_alpha = inf {t : F(t) >= alpha}                              the lower alpha-quantile
  cvar      CVaR_alpha = q - (1 / alpha) sum_k w_k E_k[(q - T)^+]          Rockafellar-Uryasev, q = q_alpha
            E_k[(q - T)^+] = sigma_k (z Phi(z) + phi(z)), z = (q - mu_k) / sigma_k;   (q - mu_k)^+ for a point mass

F is strict, so a point mass at tau does not count in p_below(tau). The infimum is the same with P(T <= t),
so q is the usual lower quantile: P(T < q) <= alpha <= P(T <= q). CVaR_alpha is the mean of T over its
worst (lowest) alpha of probability; CVaR_1 is the mean. Weights are normalised per patch (a softmax's sum
is 1 only up to rounding); a patch whose weights are not finite or sum to 0 (an unknown cell) gives NaN.

Method and cost. The anchors are shared by every patch, so anything evaluated at a common t is a matrix
product: p_below is the vector Phi_k(tau) against the weights; the quantile is bracketed by the mixture's
CDF tabulated on a shared grid (GRID_INTERVALS steps over the support plus every point mass), one product
per block of patches. A quantile at a grid point (every point mass's, so every quantile of the paper's
zero-width anchors) is exact from that table; only patches whose quantile lies between grid points in a
continuous stretch are refined, by safeguarded Newton on their Gaussian anchors with a vectorised erfc
(W. J. Cody's rational approximation): about 3 evaluations per patch on average, up to about 10 for anchors
far narrower than a grid step, to float64 rounding in practice and QUANTILE_TOLERANCE at worst. CVaR then
needs one more evaluation at q. Everything is float64 inside; results are float32.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from gcdtrav.service.engine.gcd import BLOCK_PATCHES, FloatArray, Values
from numpy.typing import ArrayLike, NDArray

Float64Array = NDArray[np.float64]

# Phi(-8.5) ~ 1e-17: no mixture has mass outside [min(mu - 8.5 sigma), max(mu + 8.5 sigma)] in float64.
SUPPORT_HALF_WIDTH = 8.5
# Uniform steps of the shared bracketing grid; more makes the table product dearer, fewer the refinement.
GRID_INTERVALS = 64
QUANTILE_TOLERANCE = 1e-7  # final bracket width; a converged Newton step is far smaller
NEWTON_STEP_TOLERANCE = 1e-8
MAX_REFINE_ITERATIONS = 100
# F within this of alpha counts as reaching it: weights that sum to 1 up to rounding still reach alpha = 1.
TIE_TOLERANCE = 1e-12

INV_SQRT_PI = 1.0 / math.sqrt(math.pi)
INV_SQRT_2 = 1.0 / math.sqrt(2.0)
INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)

# ---- erfc and the normal distribution -------------------------------------------------------------------
# W. J. Cody, "Rational Chebyshev approximations for the error function", Math. Comp. 23 (1969), as in
# netlib's specfun CALERF: erf on [0, 0.46875], erfc elsewhere. Against math.erf/math.erfc the relative error
# is below 1.5e-15 up to x = 4 and grows to about 6e-14 at x = 26 (exp(-x^2) is computed from a rounded x^2);
# tests/service/engine/test_risk.py checks it on a grid.
ERF_SMALL_END = 0.46875
ERFC_MIDDLE_END = 4.0
_ERF_A = (
    3.16112374387056560e00,
    1.13864154151050156e02,
    3.77485237685302021e02,
    3.20937758913846947e03,
    1.85777706184603153e-1,
)
_ERF_B = (2.36012909523441209e01, 2.44024637934444173e02, 1.28261652607737228e03, 2.84423683343917062e03)
_ERFC_C = (
    5.64188496988670089e-1,
    8.88314979438837594e00,
    6.61191906371416295e01,
    2.98635138197400131e02,
    8.81952221241769090e02,
    1.71204761263407058e03,
    2.05107837782607147e03,
    1.23033935479799725e03,
    2.15311535474403846e-8,
)
_ERFC_D = (
    1.57449261107098347e01,
    1.17693950891312499e02,
    5.37181101862009858e02,
    1.62138957456669019e03,
    3.29079923573345963e03,
    4.36261909014324716e03,
    3.43936767414372164e03,
    1.23033935480374942e03,
)
_ERFC_P = (
    3.05326634961232344e-1,
    3.60344899949804439e-1,
    1.25781726111229246e-1,
    1.60837851487422766e-2,
    6.58749161529837803e-4,
    1.63153871373020978e-2,
)
_ERFC_Q = (
    2.56852019228982242e00,
    1.87295284992346047e00,
    5.27905102951428412e-1,
    6.05183413124413191e-2,
    2.33520497626869185e-3,
)


def _erf_small(x: Float64Array) -> Float64Array:
    """erf(x) for |x| <= ERF_SMALL_END."""
    square = x * x
    numerator, denominator = _ERF_A[4] * square, square
    for a, b in zip(_ERF_A[:3], _ERF_B[:3], strict=True):
        numerator = (numerator + a) * square
        denominator = (denominator + b) * square
    return x * (numerator + _ERF_A[3]) / (denominator + _ERF_B[3])


def _erfc_middle(x: Float64Array, gauss: Float64Array) -> Float64Array:
    """erfc(x) for ERF_SMALL_END < x <= ERFC_MIDDLE_END, given gauss = exp(-x^2)."""
    numerator, denominator = _ERFC_C[8] * x, x
    for c, d in zip(_ERFC_C[:7], _ERFC_D[:7], strict=True):
        numerator = (numerator + c) * x
        denominator = (denominator + d) * x
    return gauss * (numerator + _ERFC_C[7]) / (denominator + _ERFC_D[7])


def _erfc_large(x: Float64Array, gauss: Float64Array) -> Float64Array:
    """erfc(x) for x > ERFC_MIDDLE_END, given gauss = exp(-x^2); 0 where exp(-x^2) underflows."""
    inverse_square = 1.0 / (x * x)
    numerator, denominator = _ERFC_P[5] * inverse_square, inverse_square
    for p, q in zip(_ERFC_P[:4], _ERFC_Q[:4], strict=True):
        numerator = (numerator + p) * inverse_square
        denominator = (denominator + q) * inverse_square
    ratio = inverse_square * (numerator + _ERFC_P[4]) / (denominator + _ERFC_Q[4])
    return gauss / x * (INV_SQRT_PI - ratio)


def _erfc_nonnegative(x: Float64Array, gauss: Float64Array) -> Float64Array:
    """erfc(x) for x >= 0, each of Cody's three ranges evaluated on its own elements only."""
    out = np.empty_like(x)
    small = x <= ERF_SMALL_END
    large = x > ERFC_MIDDLE_END
    middle = ~(small | large)
    out[small] = 1.0 - _erf_small(x[small])
    out[middle] = _erfc_middle(x[middle], gauss[middle])
    out[large] = _erfc_large(x[large], gauss[large])
    return out


def erfc(x: ArrayLike) -> Float64Array:
    """Complementary error function, elementwise, in float64 (numpy has none, scipy is not a dependency)."""
    values = np.asarray(x, dtype=np.float64)
    magnitude = np.abs(values)
    upper = _erfc_nonnegative(magnitude, np.exp(-magnitude * magnitude))
    return np.where(values < 0, 2.0 - upper, upper)


def _normal_cdf_pdf(z: Float64Array) -> tuple[Float64Array, Float64Array]:
    """Phi(z) and phi(z), sharing exp(-z^2 / 2); Phi keeps its relative accuracy in the lower tail."""
    x = np.abs(z) * INV_SQRT_2
    gauss = np.exp(-x * x)
    half_tail = 0.5 * _erfc_nonnegative(x, gauss)
    return np.where(z < 0, half_tail, 1.0 - half_tail), gauss * INV_SQRT_2PI


def normal_cdf(z: ArrayLike) -> Float64Array:
    """The standard normal CDF Phi, elementwise, in float64."""
    return _normal_cdf_pdf(np.asarray(z, dtype=np.float64))[0]


# ---- anchors and their shared tables --------------------------------------------------------------------


@dataclass(frozen=True)
class _Anchors:
    """Anchor positions and widths, split into Gaussians and point masses, with the bracketing table."""

    positions: Float64Array  # (n,)
    widths: Float64Array  # (n,)
    gaussian: NDArray[np.bool_]  # (n,): width > 0
    grid: Float64Array  # (J,): ascending, holds every point mass and both ends of the support
    cdf_at_most: Float64Array  # (n, J): P(T_k <= grid_j)
    cdf_below: Float64Array  # (n, J): P(T_k < grid_j)


def _anchor_cdfs(positions: Float64Array, widths: Float64Array, points: Float64Array) -> Float64Array:
    """(n, len(points)): each anchor's P(T_k < t); a point mass counts as below only strictly."""
    gaussian = widths > 0
    safe_widths = np.where(gaussian, widths, 1.0)[:, None]
    z = (points[None, :] - positions[:, None]) / safe_widths
    step = (positions[:, None] < points[None, :]).astype(np.float64)
    return np.where(gaussian[:, None], normal_cdf(z), step)


def _bracketing_grid(positions: Float64Array, widths: Float64Array) -> Float64Array:
    lowest = float(np.min(positions - SUPPORT_HALF_WIDTH * widths))
    highest = float(np.max(positions + SUPPORT_HALF_WIDTH * widths))
    point_masses = positions[widths == 0]
    if not (widths > 0).any():
        return np.unique(point_masses)
    return np.unique(np.concatenate([np.linspace(lowest, highest, GRID_INTERVALS + 1), point_masses]))


def _anchors(positions: Values, widths: Values, count: int) -> _Anchors:
    mu = np.asarray(positions, dtype=np.float64)
    sigma = np.asarray(widths, dtype=np.float64)
    if mu.shape != (count,) or sigma.shape != (count,):
        raise ValueError(
            f"weights have {count} anchors on axis 0 but positions have shape {mu.shape} and widths {sigma.shape}"
        )
    if not (np.isfinite(mu).all() and np.isfinite(sigma).all() and (sigma >= 0).all()):
        raise ValueError("anchor positions must be finite and widths finite and >= 0")
    grid = _bracketing_grid(mu, sigma)
    below = _anchor_cdfs(mu, sigma, grid)
    at_most = np.where((sigma == 0)[:, None], (mu[:, None] <= grid[None, :]).astype(np.float64), below)
    return _Anchors(mu, sigma, sigma > 0, grid, at_most, below)


def _check_alpha(alpha: float) -> None:
    if not 0.0 < alpha <= 1.0:
        raise ValueError(f"alpha must be in (0, 1] (the probability of the worst tail), got {alpha}")


def _check_tau(tau: float) -> None:
    if not math.isfinite(tau):
        raise ValueError(f"tau must be a finite traversability threshold, got {tau}")


# ---- per block of patches: weights (n, B) float64, each column a distribution ------------------------------


def _p_below_block(weights: Float64Array, anchors: _Anchors, tau: float) -> Float64Array:
    below = _anchor_cdfs(anchors.positions, anchors.widths, np.array([tau]))[:, 0]
    return below @ weights


def _gaussian_cdf_pdf(
    weights: Float64Array, positions: Float64Array, widths: Float64Array, t: Float64Array
) -> tuple[Float64Array, Float64Array]:
    """The Gaussian anchors' part of the mixture's CDF and density at t (one value per column)."""
    cdf, pdf = _normal_cdf_pdf((t[None, :] - positions[:, None]) / widths[:, None])
    return np.einsum("ka,ka->a", weights, cdf), np.einsum("ka,ka->a", weights / widths[:, None], pdf)


def _refine(
    weights: Float64Array,
    positions: Float64Array,
    widths: Float64Array,
    goal: Float64Array,
    low: Float64Array,
    high: Float64Array,
    start: Float64Array,
) -> Float64Array:
    """Solve G(t) = goal in (low, high) per column, G the Gaussian anchors' CDF part (continuous, increasing).

    Safeguarded Newton (as Numerical Recipes' rtsafe): a Newton step that leaves the bracket or does not halve
    the step before last becomes a bisection, so the bracket keeps shrinking where Newton stalls.
    """
    result = np.empty_like(goal)
    pending = np.arange(goal.size)
    t, previous_step, last_step = start, high - low, high - low
    for _ in range(MAX_REFINE_ITERATIONS):
        cdf, pdf = _gaussian_cdf_pdf(weights, positions, widths, t)
        below = cdf < goal
        low, high = np.where(below, t, low), np.where(below, high, t)
        with np.errstate(divide="ignore", invalid="ignore"):  # pdf 0: a NaN or infinite step, then bisection
            step = (goal - cdf) / pdf
        newton = (t + step >= low) & (t + step <= high) & (np.abs(step) <= 0.5 * np.abs(previous_step))
        step = np.where(newton, step, 0.5 * (low + high) - t)
        t = t + step
        done = (high - low <= QUANTILE_TOLERANCE) | (newton & (np.abs(step) <= NEWTON_STEP_TOLERANCE))
        result[pending[done]] = t[done]
        keep = ~done
        if not keep.any():
            return result
        pending, t, low, high, goal = pending[keep], t[keep], low[keep], high[keep], goal[keep]
        previous_step, last_step = last_step[keep], step[keep]
        weights = weights[:, keep]
    result[pending] = 0.5 * (low + high)
    return result


def _quantile_block(weights: Float64Array, anchors: _Anchors, alpha: float) -> Float64Array:
    target = alpha - TIE_TOLERANCE
    at_most = weights.T @ anchors.cdf_at_most  # (B, J): P(T <= grid_j)
    below = weights.T @ anchors.cdf_below  # (B, J): P(T < grid_j)
    reached = at_most >= target
    first = np.argmax(reached, axis=1)  # 0 where nothing is reached: fixed below
    columns = np.arange(weights.shape[1])
    found = reached[columns, first]
    first[~found] = anchors.grid.size - 1  # only rounding keeps alpha = 1 out of reach: the support's top
    q = anchors.grid[first].copy()
    # P(T < grid_j) < alpha <= P(T <= grid_j): q = grid_j exactly (a point mass, or a crossing at the grid point).
    # Otherwise F crosses alpha inside (grid_{j-1}, grid_j), where there is no point mass: F is continuous there.
    inside = found & (first > 0) & (below[columns, first] >= target)
    if inside.any() and anchors.gaussian.any():
        rows, upper = columns[inside], first[inside]
        q[rows] = _quantile_inside(
            weights[:, rows], anchors, upper, at_most[rows, upper - 1], below[rows, upper], target
        )
    return q


def _quantile_inside(
    weights: Float64Array,
    anchors: _Anchors,
    upper: NDArray[np.intp],
    cdf_low: Float64Array,
    cdf_high: Float64Array,
    target: float,
) -> Float64Array:
    """q per column where F crosses the target inside (grid[upper - 1], grid[upper]), given F at both ends."""
    g = anchors.gaussian
    low, high = anchors.grid[upper - 1], anchors.grid[upper]
    # No point mass lies inside, so theirs is a constant part of F there; the Gaussians' part is solved for.
    point_part = np.einsum("ka,ka->a", weights[~g], anchors.cdf_at_most[~g][:, upper - 1])
    goal = target - point_part
    with np.errstate(divide="ignore", invalid="ignore"):  # start by regula falsi between the table's values
        fraction = np.clip((target - cdf_low) / (cdf_high - cdf_low), 0.0, 1.0)
    start = low + np.where(np.isfinite(fraction), fraction, 0.5) * (high - low)
    return _refine(weights[g], anchors.positions[g], anchors.widths[g], goal, low, high, start)


def _cvar_block(weights: Float64Array, anchors: _Anchors, q: Float64Array, alpha: float) -> Float64Array:
    g = anchors.gaussian
    point_shortfall = np.maximum(q[None, :] - anchors.positions[~g][:, None], 0.0)
    shortfall = np.einsum("ka,ka->a", weights[~g], point_shortfall)
    if g.any():
        widths = anchors.widths[g][:, None]
        z = (q[None, :] - anchors.positions[g][:, None]) / widths
        cdf, pdf = _normal_cdf_pdf(z)
        shortfall += np.einsum("ka,ka->a", weights[g], widths * (z * cdf + pdf))
    return q - shortfall / alpha


# ---- driving the blocks --------------------------------------------------------------------------------

BlockMeasures = Callable[[Float64Array, _Anchors], Sequence[Float64Array]]


def _normalised(block: NDArray[np.floating]) -> tuple[Float64Array, NDArray[np.bool_]]:
    """The block's columns as distributions in float64; unknown columns (NaN later) become anchor 0's."""
    weights = block.astype(np.float64)
    if (weights < 0).any():
        raise ValueError("weights must be >= 0 (a distribution over the anchors per patch)")
    total = weights.sum(axis=0)
    unknown = ~(np.isfinite(total) & (total > 0))
    weights[:, unknown] = 0.0
    weights[0, unknown] = 1.0
    weights /= np.where(unknown, 1.0, total)
    return weights, unknown


def _blockwise(
    weights: FloatArray, positions: Values, widths: Values, measures: BlockMeasures, count: int
) -> list[NDArray[np.float32]]:
    w = np.asarray(weights)
    if w.ndim < 1 or w.shape[0] < 1:
        raise ValueError(f"weights need the anchors on axis 0, got shape {w.shape}")
    anchors = _anchors(positions, widths, w.shape[0])
    flat = w.reshape(w.shape[0], -1)
    outputs = [np.empty(flat.shape[1], np.float32) for _ in range(count)]
    for start in range(0, flat.shape[1], BLOCK_PATCHES):
        block = slice(start, start + BLOCK_PATCHES)
        normalised, unknown = _normalised(flat[:, block])
        for out, values in zip(outputs, measures(normalised, anchors), strict=True):
            out[block] = np.where(unknown, np.nan, values)
    return [out.reshape(w.shape[1:]) for out in outputs]


# ---- public API ----------------------------------------------------------------------------------------


def p_below(weights: FloatArray, positions: Values, widths: Values, tau: float) -> NDArray[np.float32]:
    """P(T < tau) per patch; a point mass exactly at tau does not count (strict inequality)."""
    _check_tau(tau)
    return _blockwise(weights, positions, widths, lambda w, a: [_p_below_block(w, a, tau)], 1)[0]


def quantile(weights: FloatArray, positions: Values, widths: Values, alpha: float) -> NDArray[np.float32]:
    """The lower alpha-quantile inf {t : P(T < t) >= alpha} per patch, exact at point masses, else to 1e-7.

    alpha = 1 gives the top of the support as float64 sees it: the highest point mass with weight, or where
    less than TIE_TOLERANCE of probability lies above (about mu + 7 sigma for a Gaussian anchor).
    """
    _check_alpha(alpha)
    return _blockwise(weights, positions, widths, lambda w, a: [_quantile_block(w, a, alpha)], 1)[0]


def cvar(weights: FloatArray, positions: Values, widths: Values, alpha: float) -> NDArray[np.float32]:
    """Conditional value at risk: the mean of T over its lowest alpha of probability, per patch.

    CVaR_1 is the mean; CVaR_alpha <= quantile(alpha), and it does not decrease with alpha.
    """
    _check_alpha(alpha)

    def measures(w: Float64Array, a: _Anchors) -> list[Float64Array]:
        return [_cvar_block(w, a, _quantile_block(w, a, alpha), alpha)]

    return _blockwise(weights, positions, widths, measures, 1)[0]


@dataclass(frozen=True)
class RiskMeasures:
    """Per-patch risk of the GCD; every array has the patch layout of the input weights (anchors removed)."""

    quantile: NDArray[np.float32]  # lower alpha-quantile of T
    cvar: NDArray[np.float32]  # mean of T over its lowest alpha of probability
    p_below: NDArray[np.float32]  # P(T < tau)
    alpha: float
    tau: float


def risk_measures(weights: FloatArray, positions: Values, widths: Values, alpha: float, tau: float) -> RiskMeasures:
    """quantile(alpha), cvar(alpha) and p_below(tau) in one pass, the CVaR reusing the quantile."""
    _check_alpha(alpha)
    _check_tau(tau)

    def measures(w: Float64Array, a: _Anchors) -> list[Float64Array]:
        q = _quantile_block(w, a, alpha)
        return [q, _cvar_block(w, a, q, alpha), _p_below_block(w, a, tau)]

    q, c, p = _blockwise(weights, positions, widths, measures, 3)
    return RiskMeasures(quantile=q, cvar=c, p_below=p, alpha=alpha, tau=tau)
