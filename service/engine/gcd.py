"""Gaussian Context Distribution (GCD) statistics, vectorised over every patch.

Inputs are logits or weights with the anchors on axis 0 and any patch layout after it: ``(n, h, w)`` for
an image, ``(n, k)`` for a list of patches. Nothing here knows about models or middleware.

For patch weights w_k, anchor positions p_k and anchor widths sigma_k the GCD is the mixture
sum_k w_k N(x; p_k, sigma_k^2) on the traversability scale. Its moments have closed forms, used below:
  mean        mu      = sum w_k p_k
  variance    sigma^2 = sum w_k (d_k^2 + sigma_k^2)                           with d_k = p_k - mu
  3rd central m3      = sum w_k (d_k^3 + 3 d_k sigma_k^2)
  4th central m4      = sum w_k (d_k^4 + 6 d_k^2 sigma_k^2 + 3 sigma_k^4)
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.floating]
# Anchor positions and widths arrive as the AnchorSet's lists or as arrays; each function converts them.
Values = ArrayLike

# Below this spread a distribution is a point mass: skewness and kurtosis are reported as 0.
DEGENERATE_STD = 1e-6
# Zero-width anchors are Dirac spikes; to draw a density and count its modes each component is given at
# least this width (about half the gap between neighbouring anchors of the paper's set).
DEFAULT_DENSITY_BANDWIDTH = 0.025
DEFAULT_DENSITY_GRID = 201
# A local maximum counts as a mode when it reaches this fraction of the highest peak.
MODE_RELATIVE_HEIGHT = 0.05


# Patches per block of the fused passes below: a block's (n, 4096) float32 weights stay in the L2 cache
# while softmax and moments run over it (about 2x faster than whole-image passes for 13 x 352 x 352).
BLOCK_PATCHES = 4096


def _patch_blocks(count: int) -> range:
    return range(0, count, BLOCK_PATCHES)


def _softmax_block(logits: NDArray[np.float32], out: NDArray[np.float32], temperature: float) -> None:
    # Non-finite logits give NaN weights without a warning per block; callers check their results.
    with np.errstate(invalid="ignore"):
        if temperature != 1.0:
            np.divide(logits, np.float32(temperature), out=out)
            np.subtract(out, out.max(axis=0), out=out)
        else:
            np.subtract(logits, logits.max(axis=0), out=out)
        np.exp(out, out=out)
        out *= np.reciprocal(out.sum(axis=0))  # one division per patch, not per weight


def _check_temperature(temperature: float) -> None:
    if not temperature > 0:
        raise ValueError(f"temperature must be > 0, got {temperature}")


def softmax_weights(logits: FloatArray, temperature: float = 1.0) -> NDArray[np.float32]:
    """Per-patch softmax over the anchor axis (axis 0); invariant to adding a constant per patch."""
    _check_temperature(temperature)
    scores = np.asarray(logits, dtype=np.float32)
    flat = scores.reshape(scores.shape[0], -1)
    weights = np.empty_like(flat)
    for start in _patch_blocks(flat.shape[1]):
        block = slice(start, start + BLOCK_PATCHES)
        _softmax_block(flat[:, block], weights[:, block], temperature)
    return weights.reshape(scores.shape)


def _moment_rows(positions: Values, widths: Values) -> NDArray[np.float64]:
    """(2, n): each anchor's first and second raw moment, p and p^2 + sigma^2."""
    p = np.asarray(positions, dtype=np.float64)
    s = np.asarray(widths, dtype=np.float64)
    return np.stack([p, p * p + s * s])


def _mean_std_block(
    weights: NDArray[np.float32], moment_rows: NDArray[np.float64], mean: NDArray[np.float32], std: NDArray[np.float32]
) -> None:
    # E[x] and E[x^2] in one float64 product: float64 keeps E[x^2] - E[x]^2 exact to float32
    # precision even for a single dominant anchor (variance 0).
    moments = moment_rows @ weights
    mean[:] = np.clip(moments[0], 0.0, 1.0)
    std[:] = np.sqrt(np.maximum(moments[1] - moments[0] * moments[0], 0.0))


def mixture_mean_std(
    weights: FloatArray, positions: Values, widths: Values
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """T and U as the paper defines them: the mixture's mean and standard deviation."""
    w = np.asarray(weights, dtype=np.float32)
    flat = w.reshape(w.shape[0], -1)
    rows = _moment_rows(positions, widths)
    mean, std = np.empty(flat.shape[1], np.float32), np.empty(flat.shape[1], np.float32)
    for start in _patch_blocks(flat.shape[1]):
        block = slice(start, start + BLOCK_PATCHES)
        _mean_std_block(flat[:, block], rows, mean[block], std[block])
    return mean.reshape(w.shape[1:]), std.reshape(w.shape[1:])


def softmax_mean_std(
    logits: FloatArray, positions: Values, widths: Values, temperature: float = 1.0
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
    """Weights, T and U in one pass over cache-sized blocks of patches.

    The same numbers as ``softmax_weights`` followed by ``mixture_mean_std``, without reading the weights
    back from memory: this is the service's per-frame path.
    """
    _check_temperature(temperature)
    scores = np.asarray(logits, dtype=np.float32)
    flat = scores.reshape(scores.shape[0], -1)
    rows = _moment_rows(positions, widths)
    weights = np.empty_like(flat)
    mean, std = np.empty(flat.shape[1], np.float32), np.empty(flat.shape[1], np.float32)
    for start in _patch_blocks(flat.shape[1]):
        block = slice(start, start + BLOCK_PATCHES)
        _softmax_block(flat[:, block], weights[:, block], temperature)
        _mean_std_block(weights[:, block], rows, mean[block], std[block])
    shape = scores.shape[1:]
    return weights.reshape(scores.shape), mean.reshape(shape), std.reshape(shape)


def _column(values: Values, ndim: int) -> NDArray[np.float32]:
    """Shape an (n,) anchor vector to broadcast against an (n, ...) weight array."""
    return np.asarray(values, dtype=np.float32).reshape((-1,) + (1,) * (ndim - 1))


def max_mixture_std(positions: Values, widths: Values) -> float:
    """The largest standard deviation any weighting of these anchors can produce.

    The variance sum w_k a_k - (sum w_k p_k)^2 (a_k = p_k^2 + sigma_k^2) is concave in w; for a fixed mean
    its maximum over the simplex is a linear program with two equality constraints, so an optimum uses at
    most two anchors. Checking every pair (and every single anchor) is therefore exact.
    """
    p = np.asarray(positions, dtype=np.float64)
    a = p * p + np.asarray(widths, dtype=np.float64) ** 2
    best = float(np.max(a - p * p))
    for i, j in combinations(range(len(p)), 2):
        if p[i] == p[j]:
            continue
        # Mixing t of anchor i with 1 - t of anchor j; the variance is a concave quadratic in t.
        t = ((a[i] - a[j]) / (2 * (p[i] - p[j])) - p[j]) / (p[i] - p[j])
        t = min(max(t, 0.0), 1.0)
        mean = t * p[i] + (1 - t) * p[j]
        best = max(best, t * a[i] + (1 - t) * a[j] - mean * mean)
    return float(np.sqrt(best))


@dataclass(frozen=True)
class MixtureStatistics:
    """Per-patch statistics; every array has the patch layout of the input weights (anchors removed)."""

    mean: NDArray[np.float32]
    std: NDArray[np.float32]
    skewness: NDArray[np.float32]
    excess_kurtosis: NDArray[np.float32]
    entropy: NDArray[np.float32]
    modes: NDArray[np.int32]
    top_anchors: NDArray[np.int64]  # (k, ...): indices of the k largest weights, largest first


def mixture_statistics(
    weights: FloatArray,
    positions: Values,
    widths: Values,
    top_k: int = 3,
    bandwidth: float = DEFAULT_DENSITY_BANDWIDTH,
) -> MixtureStatistics:
    """The paper's mean and std plus the higher moments, entropy, modes and top anchors it leaves open."""
    w = np.asarray(weights, dtype=np.float32)
    mean, std = mixture_mean_std(w, positions, widths)
    d = _column(positions, w.ndim) - mean
    s2 = _column(widths, w.ndim) ** 2
    m3 = np.einsum("k...,k...->...", w, d**3 + 3 * d * s2, dtype=np.float32)
    m4 = np.einsum("k...,k...->...", w, d**4 + 6 * d * d * s2 + 3 * s2 * s2, dtype=np.float32)
    spread = std > DEGENERATE_STD
    safe_std = np.where(spread, std, 1.0)
    skewness = np.where(spread, m3 / safe_std**3, 0.0).astype(np.float32)
    kurtosis = np.where(spread, m4 / safe_std**4 - 3.0, 0.0).astype(np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        entropy = -np.sum(np.where(w > 0, w * np.log(w), 0.0), axis=0, dtype=np.float32)
    k = min(top_k, w.shape[0])
    top = np.argsort(-w, axis=0, kind="stable")[:k]
    return MixtureStatistics(
        mean=mean,
        std=std,
        skewness=skewness,
        excess_kurtosis=kurtosis,
        entropy=np.asarray(entropy, dtype=np.float32),
        modes=count_modes(w, positions, widths, bandwidth=bandwidth),
        top_anchors=top,
    )


def density_grid(size: int = DEFAULT_DENSITY_GRID) -> NDArray[np.float32]:
    return np.linspace(0.0, 1.0, size, dtype=np.float32)


def _component_kernels(positions: Values, widths: Values, grid: FloatArray, bandwidth: float) -> NDArray[np.float32]:
    """(n, G): each anchor's normal density on the grid, widths floored at ``bandwidth``."""
    p = np.asarray(positions, dtype=np.float32)[:, None]
    s = np.maximum(np.asarray(widths, dtype=np.float32), np.float32(bandwidth))[:, None]
    z = (np.asarray(grid, dtype=np.float32)[None, :] - p) / s
    return np.asarray(np.exp(-0.5 * z * z) / (s * np.sqrt(2 * np.pi)), dtype=np.float32)


def mixture_density(
    weights: FloatArray,
    positions: Values,
    widths: Values,
    grid: FloatArray | None = None,
    bandwidth: float = DEFAULT_DENSITY_BANDWIDTH,
) -> NDArray[np.float32]:
    """The GCD's density sampled on ``grid``: shape (..., G) for weights of shape (n, ...)."""
    grid = density_grid() if grid is None else np.asarray(grid, dtype=np.float32)
    kernels = _component_kernels(positions, widths, grid, bandwidth)
    w = np.asarray(weights, dtype=np.float32)
    return np.tensordot(w, kernels, axes=(0, 0)).astype(np.float32)


def count_modes(
    weights: FloatArray,
    positions: Values,
    widths: Values,
    bandwidth: float = DEFAULT_DENSITY_BANDWIDTH,
    grid_size: int = DEFAULT_DENSITY_GRID,
    chunk: int = 16384,
) -> NDArray[np.int32]:
    """Number of peaks of the mixture density (on [0, 1], at least ``MODE_RELATIVE_HEIGHT`` of the top)."""
    w = np.asarray(weights, dtype=np.float32)
    flat = w.reshape(w.shape[0], -1)
    kernels = _component_kernels(positions, widths, density_grid(grid_size), bandwidth)
    out = np.empty(flat.shape[1], dtype=np.int32)
    for start in range(0, flat.shape[1], chunk):  # chunked so the (patches, G) density stays small
        density = flat[:, start : start + chunk].T @ kernels
        padded = np.pad(density, ((0, 0), (1, 1)), constant_values=-1.0)
        centre = padded[:, 1:-1]
        # A plateau counts once: strictly above the left neighbour, at least the right one.
        peak = (centre > padded[:, :-2]) & (centre >= padded[:, 2:])
        peak &= centre >= MODE_RELATIVE_HEIGHT * density.max(axis=1, keepdims=True)
        out[start : start + chunk] = peak.sum(axis=1)
    return out.reshape(w.shape[1:])


# ---- the paper's baselines -------------------------------------------------------------------------


def argmax_baseline(weights: FloatArray, positions: Values) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """'CLIP' baseline: T = position of the top anchor, uncertainty = 1 - its weight."""
    w = np.asarray(weights, dtype=np.float32)
    top = np.argmax(w, axis=0)
    t = np.asarray(positions, dtype=np.float32)[top]
    u = 1.0 - np.take_along_axis(w, top[None], axis=0)[0]
    return t.astype(np.float32), u.astype(np.float32)


def gaussian_fit_baseline(
    weights: FloatArray, positions: Values, iterations: int = 25
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Unimodal ablation: one Gaussian A exp(-(p - m)^2 / 2 s^2) fitted by least squares to (p_k, w_k).

    Levenberg-Marquardt on all patches at once (parameters A, m, log s), started from the weighted
    moments. T = m clipped to [0, 1], U = s.
    """
    w = np.asarray(weights, dtype=np.float64)
    shape = w.shape[1:]
    y = w.reshape(w.shape[0], -1).T  # (P, n)
    p = np.asarray(positions, dtype=np.float64)[None, :]
    mean0 = (y * p).sum(axis=1)
    std0 = np.sqrt(np.maximum((y * (p - mean0[:, None]) ** 2).sum(axis=1), 0.0))
    theta = np.stack([y.max(axis=1), mean0, np.log(np.clip(std0, 0.01, 1.0))], axis=1)
    damping = np.full(len(y), 1e-2)

    def residuals(params: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        amp, mu, s = params[:, :1], params[:, 1:2], np.exp(params[:, 2:3])
        gauss = np.exp(-0.5 * ((p - mu) / s) ** 2)
        return amp * gauss - y, gauss

    res, gauss = residuals(theta)
    cost = (res**2).sum(axis=1)
    for _ in range(iterations):
        amp, mu, s = theta[:, :1], theta[:, 1:2], np.exp(theta[:, 2:3])
        jac = np.stack([gauss, amp * gauss * (p - mu) / s**2, amp * gauss * (p - mu) ** 2 / s**2], axis=2)  # (P, n, 3)
        jtj = np.einsum("pki,pkj->pij", jac, jac)
        jtr = np.einsum("pki,pk->pi", jac, res)
        diag = np.einsum("pii->pi", jtj)
        lhs = jtj + (damping[:, None] * (diag + 1e-12))[:, :, None] * np.eye(3)[None]
        step = np.linalg.solve(lhs, -jtr[:, :, None])[:, :, 0]
        trial = theta + step
        trial[:, 2] = np.clip(trial[:, 2], np.log(1e-3), np.log(2.0))
        trial_res, trial_gauss = residuals(trial)
        trial_cost = (trial_res**2).sum(axis=1)
        better = np.isfinite(trial_cost) & (trial_cost < cost)
        theta = np.where(better[:, None], trial, theta)
        res = np.where(better[:, None], trial_res, res)
        gauss = np.where(better[:, None], trial_gauss, gauss)
        cost = np.where(better, trial_cost, cost)
        damping = np.where(better, damping / 3.0, np.minimum(damping * 4.0, 1e8))
    t = np.clip(theta[:, 1], 0.0, 1.0).reshape(shape)
    u = np.exp(theta[:, 2]).reshape(shape)
    return t.astype(np.float32), u.astype(np.float32)
