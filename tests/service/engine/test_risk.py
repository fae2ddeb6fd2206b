from __future__ import annotations

import math
from statistics import NormalDist

import numpy as np
import pytest
from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.service.engine import gcd, risk
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from benchmarks.risk_mc import sample, shortfall_standard_error

PAPER = default_anchor_set()
STANDARD_NORMAL = NormalDist()
# float32 results: a quantile is within QUANTILE_TOLERANCE plus one float32 rounding of the exact one.
OUTPUT_SLACK = 1e-6


# ---- references: plain Python, one patch at a time --------------------------------------------------------


def normalised(weights: np.ndarray) -> np.ndarray:
    w = np.asarray(weights, dtype=np.float64)
    return w / w.sum(axis=0)


def reference_cdf(w: np.ndarray, mu: np.ndarray, sigma: np.ndarray, t: float, strict: bool = True) -> float:
    """P(T < t) (strict) or P(T <= t) for one patch, with math.erfc."""
    total = 0.0
    for wk, m, s in zip(w, mu, sigma, strict=True):
        if s > 0:
            total += wk * 0.5 * math.erfc((m - t) / (s * math.sqrt(2.0)))
        else:
            total += wk * float(m < t if strict else m <= t)
    return total


def reference_quantile(w: np.ndarray, mu: np.ndarray, sigma: np.ndarray, alpha: float) -> float:
    """inf {t : P(T <= t) >= alpha} by bisection to float64 rounding, with risk.py's tie tolerance."""
    low = float(np.min(mu - 8.5 * sigma)) - 1.0
    high = float(np.max(mu + 8.5 * sigma))
    for _ in range(80):
        middle = 0.5 * (low + high)
        if reference_cdf(w, mu, sigma, middle, strict=False) >= alpha - risk.TIE_TOLERANCE:
            high = middle
        else:
            low = middle
    return high


def reference_shortfall(w: np.ndarray, mu: np.ndarray, sigma: np.ndarray, q: float) -> float:
    """E[(q - T)^+] for one patch."""
    total = 0.0
    for wk, m, s in zip(w, mu, sigma, strict=True):
        if s > 0:
            z = (q - m) / s
            total += wk * s * (z * STANDARD_NORMAL.cdf(z) + STANDARD_NORMAL.pdf(z))
        else:
            total += wk * max(q - m, 0.0)
    return total


# ---- erf, erfc and Phi ------------------------------------------------------------------------------------


def test_erfc_matches_math_over_its_whole_range() -> None:
    x = np.concatenate([np.linspace(-6.0, 6.0, 4001), np.linspace(6.0, 26.5, 2001), [0.0, 0.46875, 4.0]])
    expected = np.array([math.erfc(v) for v in x])
    relative = np.abs(risk.erfc(x) - expected) / expected
    assert relative[np.abs(x) <= 4].max() < 2e-15
    assert relative.max() < 1e-13


def test_normal_cdf_matches_math() -> None:
    x = np.linspace(-9.0, 9.0, 3601)
    np.testing.assert_allclose(risk.normal_cdf(x), [STANDARD_NORMAL.cdf(v) for v in x], rtol=1e-13, atol=1e-16)
    assert risk.erfc(np.inf) == 0.0 and risk.erfc(-np.inf) == 2.0 and np.isnan(risk.erfc(np.nan))


# ---- closed forms and hand-made cases ------------------------------------------------------------------------


@pytest.mark.parametrize("alpha", [1e-6, 0.05, 0.5, 0.9])
def test_one_gaussian_anchor_has_closed_forms(alpha: float) -> None:
    mu, sigma = 0.6, 0.08
    z = STANDARD_NORMAL.inv_cdf(alpha)
    m = risk.risk_measures(np.array([1.0]), [mu], [sigma], alpha, tau=0.5)
    assert float(m.quantile) == pytest.approx(mu + sigma * z, abs=1e-6)
    assert float(m.cvar) == pytest.approx(mu - sigma * STANDARD_NORMAL.pdf(z) / alpha, abs=1e-6)
    assert float(m.p_below) == pytest.approx(STANDARD_NORMAL.cdf((0.5 - mu) / sigma), abs=1e-7)


def test_puddle_edge_gets_a_far_lower_cvar_than_its_mean() -> None:
    weights = np.array([0.5, 0.5], np.float32)  # grass at 0.7, water at 0.02: the patch is one or the other
    positions, widths = [0.7, 0.02], [0.0, 0.0]
    mean, _ = gcd.mixture_mean_std(weights, positions, widths)
    m = risk.risk_measures(weights, positions, widths, alpha=0.1, tau=0.1)
    assert float(mean) == pytest.approx(0.36)
    assert float(m.quantile) == pytest.approx(0.02) and float(m.cvar) == pytest.approx(0.02)
    assert float(m.p_below) == pytest.approx(0.5)
    # Past the water's half, the grass enters the tail's mean: (0.5 * 0.02 + 0.25 * 0.7) / 0.75.
    assert float(risk.cvar(weights, positions, widths, 0.75)) == pytest.approx((0.01 + 0.175) / 0.75, abs=1e-6)


def test_puddle_with_wide_anchors_keeps_its_low_tail() -> None:
    weights = np.array([0.5, 0.5])
    m = risk.risk_measures(weights, [0.7, 0.02], [0.05, 0.05], alpha=0.1, tau=0.1)
    assert float(m.cvar) < 0.02 < 0.36 - 0.3
    assert float(m.p_below) == pytest.approx(0.5 * STANDARD_NORMAL.cdf(0.08 / 0.05), abs=1e-7)


def test_point_mass_quantiles_are_the_anchor_positions() -> None:
    positions = np.asarray(PAPER.positions)
    weights = np.zeros(len(positions))
    weights[[1, 6, 11]] = [0.2, 0.5, 0.3]  # mud 0.1, grass 0.5, asphalt 0.98
    for alpha, expected in [(1e-6, 0.1), (0.2, 0.1), (0.2000001, 0.5), (0.7, 0.5), (0.71, 0.98), (1.0, 0.98)]:
        assert float(risk.quantile(weights, positions, PAPER.widths, alpha)) == np.float32(expected), alpha


def test_alpha_one_gives_the_mean_and_the_top_of_the_support() -> None:
    weights = np.array([0.25, 0.25, 0.5], np.float32)
    positions, widths = [0.1, 0.5, 0.9], [0.0, 0.1, 0.0]
    mean, _ = gcd.mixture_mean_std(weights, positions, widths)
    assert float(risk.cvar(weights, positions, widths, 1.0)) == pytest.approx(float(mean), abs=1e-6)
    # A Gaussian has no top: alpha = 1 stops where less than 1e-12 of probability lies above, 0.25 Q(z) = 1e-12.
    top = 0.5 - 0.1 * STANDARD_NORMAL.inv_cdf(1e-12 / 0.25)
    assert float(risk.quantile(weights, positions, widths, 1.0)) == pytest.approx(top, abs=1e-4)
    assert float(risk.quantile(weights, positions, [0.0, 0.0, 0.0], 1.0)) == np.float32(0.9)


def test_tiny_alpha_gives_the_lowest_anchor_with_weight() -> None:
    weights = np.array([0.0, 0.3, 0.7])
    assert float(risk.cvar(weights, [0.0, 0.4, 0.8], [0.0, 0.0, 0.0], 1e-6)) == np.float32(0.4)
    m = risk.risk_measures(weights, [0.0, 0.4, 0.8], [0.0, 0.05, 0.0], alpha=1e-6, tau=0.5)
    z = STANDARD_NORMAL.inv_cdf(1e-6 / 0.3)
    assert float(m.quantile) == pytest.approx(0.4 + 0.05 * z, abs=1e-6)
    assert float(m.cvar) == pytest.approx(0.4 - 0.05 * STANDARD_NORMAL.pdf(z) / (1e-6 / 0.3), abs=1e-6)


def test_all_weight_on_one_anchor() -> None:
    weights = np.zeros((13, 2))
    weights[7, :] = 1.0  # gravel, 0.6
    widths = [0.0] * 13
    for alpha in (1e-6, 0.3, 1.0):
        m = risk.risk_measures(weights, PAPER.positions, widths, alpha, tau=0.6)
        np.testing.assert_array_equal(m.quantile, np.float32(0.6))
        np.testing.assert_array_equal(m.cvar, np.float32(0.6))
        np.testing.assert_array_equal(m.p_below, 0.0)  # a point mass at tau is not below it


def test_tau_below_and_above_every_anchor() -> None:
    weights = gcd.softmax_weights(np.random.default_rng(3).normal(0, 2, (13, 4, 5)))
    concrete = weights[-1]  # the point mass at 1.0: not below tau = 1 (strict), below anything above it
    np.testing.assert_array_equal(risk.p_below(weights, PAPER.positions, PAPER.widths, 0.0), 0.0)
    np.testing.assert_allclose(risk.p_below(weights, PAPER.positions, PAPER.widths, 1.0), 1.0 - concrete, atol=1e-6)
    np.testing.assert_allclose(risk.p_below(weights, PAPER.positions, PAPER.widths, 1.0001), 1.0, atol=1e-6)
    wide = [0.05] * 13
    assert risk.p_below(weights, PAPER.positions, wide, -1.0).max() < 1e-15
    np.testing.assert_allclose(risk.p_below(weights, PAPER.positions, wide, 2.0), 1.0, atol=1e-6)


# ---- properties over random mixtures ---------------------------------------------------------------------


@st.composite
def mixtures(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(n, 3) float32 weights of three patches, positions in [0, 1], widths 0 (point masses) or Gaussian."""
    n = draw(st.integers(1, 6))
    weights = draw(arrays(np.float32, (n, 3), elements=st.floats(0.0, 1.0, width=32)))
    assume((weights.sum(axis=0) > 1e-3).all())
    positions = draw(arrays(np.float64, n, elements=st.floats(0.0, 1.0)))
    widths = draw(arrays(np.float64, n, elements=st.one_of(st.just(0.0), st.floats(1e-3, 0.3))))
    return weights, positions, widths


ALPHAS = st.one_of(st.sampled_from([1e-6, 0.5, 1.0]), st.floats(1e-4, 1.0))


@settings(max_examples=150, deadline=None, derandomize=True)
@given(mixture=mixtures(), alpha=ALPHAS)
def test_quantile_is_the_lower_alpha_quantile(mixture: tuple[np.ndarray, ...], alpha: float) -> None:
    weights, positions, widths = mixture
    q = risk.quantile(weights, positions, widths, alpha)
    for patch, w in enumerate(normalised(weights).T):
        t = float(q[patch])
        assert reference_cdf(w, positions, widths, t + OUTPUT_SLACK, strict=False) >= alpha - 1e-9
        if alpha < 1.0:  # alpha = 1 of a Gaussian is its support's top, where F is 1 below as well
            assert reference_cdf(w, positions, widths, t - OUTPUT_SLACK) < alpha


@settings(max_examples=150, deadline=None, derandomize=True)
@given(mixture=mixtures(), alpha=ALPHAS)
def test_cvar_matches_the_rockafellar_uryasev_reference(mixture: tuple[np.ndarray, ...], alpha: float) -> None:
    weights, positions, widths = mixture
    m = risk.risk_measures(weights, positions, widths, alpha, tau=0.5)
    assert (m.cvar <= m.quantile).all()
    for patch, w in enumerate(normalised(weights).T):
        q = reference_quantile(w, positions, widths, alpha)
        # At alpha = 1 (or within 1e-9 of it: hypothesis found 1 - 1e-16), a Gaussian's q sits where its density
        # is ~1e-11: float64 fixes it to ~1e-5 only. The CVaR below is still exact there.
        if alpha < 1.0 - 1e-9:
            assert float(m.quantile[patch]) == pytest.approx(q, abs=OUTPUT_SLACK)
        expected = q - reference_shortfall(w, positions, widths, q) / alpha
        assert float(m.cvar[patch]) == pytest.approx(expected, abs=1e-6)
        assert float(m.p_below[patch]) == pytest.approx(reference_cdf(w, positions, widths, 0.5), abs=1e-7)


@settings(max_examples=100, deadline=None, derandomize=True)
@given(mixture=mixtures())
def test_cvar_rises_with_alpha_to_the_mean(mixture: tuple[np.ndarray, ...]) -> None:
    weights, positions, widths = mixture
    alphas = [1e-6, 1e-3, 0.05, 0.2, 0.5, 0.8, 0.99, 1.0]
    values = np.stack([risk.cvar(weights, positions, widths, a) for a in alphas])
    assert (np.diff(values, axis=0) >= -1e-6).all()
    mean, _ = gcd.mixture_mean_std(normalised(weights).astype(np.float32), positions, widths)
    np.testing.assert_allclose(values[-1], mean, atol=1e-6)


def test_anchor_order_does_not_matter(rng: np.random.Generator) -> None:
    weights = gcd.softmax_weights(rng.normal(0, 2, (13, 40)))
    widths = rng.choice([0.0, 0.04], 13)
    order = rng.permutation(13)
    a = risk.risk_measures(weights, PAPER.positions, widths, 0.2, 0.3)
    b = risk.risk_measures(weights[order], np.asarray(PAPER.positions)[order], widths[order], 0.2, 0.3)
    np.testing.assert_allclose(a.quantile, b.quantile, atol=1e-6)
    np.testing.assert_allclose(a.cvar, b.cvar, atol=1e-6)
    np.testing.assert_allclose(a.p_below, b.p_below, atol=1e-6)


# ---- Monte Carlo ------------------------------------------------------------------------------------------


def test_agrees_with_monte_carlo_including_point_masses() -> None:
    """Every measure within 5 Monte Carlo standard errors (benchmarks/risk_mc.py reports them at 10^6 samples)."""
    rng = np.random.default_rng(20261123)
    count = 200_000
    for _ in range(4):
        n = 6
        w = rng.dirichlet(np.full(n, 0.7))
        mu = rng.uniform(0.0, 1.0, n)
        sigma = np.where(rng.random(n) < 0.5, 0.0, rng.uniform(0.01, 0.15, n))
        samples = sample(rng, w, mu, sigma, count)
        for alpha in (0.01, 0.1, 0.5):
            m = risk.risk_measures(w, mu, sigma, alpha, tau=0.3)
            q, c = float(m.quantile), float(m.cvar)
            se = math.sqrt(alpha * (1 - alpha) / count)
            assert np.mean(samples < q - OUTPUT_SLACK) <= alpha + 5 * se
            assert np.mean(samples <= q + OUTPUT_SLACK) >= alpha - 5 * se
            # The standard error from the mixture's own variance: a rare tail's few samples cannot estimate theirs.
            se = shortfall_standard_error(w, mu, sigma, q, alpha, count)
            assert abs(c - (q - np.maximum(q - samples, 0.0).mean() / alpha)) <= 5 * se + OUTPUT_SLACK
            p = float(m.p_below)
            assert abs(p - np.mean(samples < 0.3)) <= 5 * math.sqrt(max(p * (1 - p), 1e-12) / count) + 1e-6


# ---- shapes, blocks, unknown patches and bad inputs --------------------------------------------------------------


@pytest.mark.parametrize("patch_shape", [(), (7,), (3, 4)])
def test_shapes_and_dtype(patch_shape: tuple[int, ...]) -> None:
    weights = gcd.softmax_weights(np.random.default_rng(0).normal(0, 2, (13, *patch_shape)))
    m = risk.risk_measures(weights, PAPER.positions, [0.03] * 13, 0.1, 0.2)
    for values in (m.quantile, m.cvar, m.p_below):
        assert values.shape == patch_shape and values.dtype == np.float32
    assert risk.quantile(weights, PAPER.positions, PAPER.widths, 0.1).shape == patch_shape


def test_blocks_give_the_same_values_as_single_patches(rng: np.random.Generator) -> None:
    weights = gcd.softmax_weights(rng.normal(0, 2, (5, gcd.BLOCK_PATCHES + 37)))
    positions, widths = [0.05, 0.3, 0.5, 0.7, 0.95], [0.0, 0.04, 0.0, 0.1, 0.0]
    whole = risk.risk_measures(weights, positions, widths, 0.15, 0.4)
    for patch in (0, gcd.BLOCK_PATCHES - 1, gcd.BLOCK_PATCHES, gcd.BLOCK_PATCHES + 36):
        single = risk.risk_measures(weights[:, patch], positions, widths, 0.15, 0.4)
        assert whole.quantile[patch] == pytest.approx(float(single.quantile), abs=1e-7)
        assert whole.cvar[patch] == pytest.approx(float(single.cvar), abs=1e-7)
        assert whole.p_below[patch] == single.p_below


def test_unknown_patches_are_nan_and_weights_are_normalised() -> None:
    weights = np.array([[0.0, np.nan, 2.0], [0.0, 0.5, 2.0]])
    m = risk.risk_measures(weights, [0.2, 0.8], [0.0, 0.0], 0.5, 0.5)
    assert np.isnan(m.quantile[:2]).all() and np.isnan(m.cvar[:2]).all() and np.isnan(m.p_below[:2]).all()
    assert m.quantile[2] == np.float32(0.2) and m.p_below[2] == 0.5 and m.cvar[2] == np.float32(0.2)


@pytest.mark.parametrize("alpha", [0.0, -0.1, 1.0000001, math.nan, math.inf])
def test_bad_alpha_is_refused(alpha: float) -> None:
    with pytest.raises(ValueError, match="alpha must be in"):
        risk.cvar(np.ones(2), [0.2, 0.8], [0.0, 0.0], alpha)
    with pytest.raises(ValueError, match="alpha must be in"):
        risk.quantile(np.ones(2), [0.2, 0.8], [0.0, 0.0], alpha)


@pytest.mark.parametrize("tau", [math.nan, math.inf, -math.inf])
def test_bad_tau_is_refused(tau: float) -> None:
    with pytest.raises(ValueError, match="tau must be a finite"):
        risk.p_below(np.ones(2), [0.2, 0.8], [0.0, 0.0], tau)
    with pytest.raises(ValueError, match="tau must be a finite"):
        risk.risk_measures(np.ones(2), [0.2, 0.8], [0.0, 0.0], 0.5, tau)


def test_bad_anchors_and_weights_are_refused() -> None:
    with pytest.raises(ValueError, match="3 anchors on axis 0"):
        risk.quantile(np.ones((3, 4)), [0.2, 0.8], [0.0, 0.0], 0.5)
    with pytest.raises(ValueError, match="widths finite and >= 0"):
        risk.quantile(np.ones(2), [0.2, 0.8], [0.0, -0.1], 0.5)
    with pytest.raises(ValueError, match="weights must be >= 0"):
        risk.quantile(np.array([1.0, -0.5]), [0.2, 0.8], [0.0, 0.0], 0.5)
