from __future__ import annotations

import numpy as np
import pytest
from gcdtrav.schemas.anchors import Anchor, AnchorSet, default_anchor_set
from gcdtrav.schemas.config import EngineSettings, Method
from gcdtrav.service.engine import gcd
from gcdtrav.service.engine.maps import compute_maps
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

PAPER = default_anchor_set()
P = np.asarray(PAPER.positions, np.float32)


def anchor_set(positions: list[float], widths: list[float] | None = None) -> AnchorSet:
    widths = widths or [0.0] * len(positions)
    return AnchorSet(
        anchors=[
            Anchor(concept=f"c{i}", position=p, width=w) for i, (p, w) in enumerate(zip(positions, widths, strict=True))
        ]
    )


def test_one_dominant_anchor_gives_its_position_and_width() -> None:
    cas = anchor_set([0.1, 0.6, 0.9], [0.0, 0.07, 0.0])
    logits = np.array([0.0, 60.0, 0.0], np.float32).reshape(3, 1, 1)
    maps = compute_maps(logits, cas, EngineSettings())
    assert maps.traversability[0, 0] == pytest.approx(0.6, abs=1e-6)
    assert maps.uncertainty[0, 0] == pytest.approx(0.07, abs=1e-6)


def test_two_equal_peaks_at_the_ends() -> None:
    cas = anchor_set([0.0, 0.5, 1.0])
    logits = np.array([8.0, -80.0, 8.0], np.float32).reshape(3, 1, 1)
    maps = compute_maps(logits, cas, EngineSettings())
    assert maps.traversability[0, 0] == pytest.approx(0.5, abs=1e-6)
    assert maps.uncertainty[0, 0] == pytest.approx(0.5, abs=1e-6)
    normalized = compute_maps(logits, cas, EngineSettings(normalize_uncertainty=True))
    assert normalized.uncertainty[0, 0] == pytest.approx(1.0, abs=1e-5)


def test_hand_computed_three_anchor_mixture() -> None:
    # w = (0.2, 0.3, 0.5) at p = (0, 0.5, 1), widths (0.1, 0, 0.2):
    # mu = 0.15 + 0.5 = 0.65; E[x^2] = 0.2*0.01 + 0.3*0.25 + 0.5*(1 + 0.04) = 0.597; var = 0.597 - 0.4225 = 0.1745
    cas = anchor_set([0.0, 0.5, 1.0], [0.1, 0.0, 0.2])
    logits = np.log(np.array([0.2, 0.3, 0.5], np.float32)).reshape(3, 1)
    maps = compute_maps(logits, cas, EngineSettings())
    assert maps.traversability[0] == pytest.approx(0.65, abs=1e-6)
    assert maps.uncertainty[0] == pytest.approx(np.sqrt(0.1745), abs=1e-6)


def test_constant_offset_changes_nothing(rng: np.random.Generator) -> None:
    logits = rng.normal(0, 3, size=(13, 8, 9)).astype(np.float32)
    a = compute_maps(logits, PAPER, EngineSettings())
    b = compute_maps(logits + 17.5, PAPER, EngineSettings())
    np.testing.assert_allclose(a.traversability, b.traversability, atol=1e-6)
    np.testing.assert_allclose(a.uncertainty, b.uncertainty, atol=1e-6)


def test_permuting_anchors_with_logits_changes_nothing(rng: np.random.Generator) -> None:
    positions = np.sort(rng.uniform(0, 1, 6))
    widths = rng.uniform(0, 0.1, 6)
    logits = rng.normal(0, 3, size=(6, 5, 4)).astype(np.float32)
    order = rng.permutation(6)
    t1, u1 = gcd.mixture_mean_std(gcd.softmax_weights(logits), positions, widths)
    t2, u2 = gcd.mixture_mean_std(gcd.softmax_weights(logits[order]), positions[order], widths[order])
    np.testing.assert_allclose(t1, t2, atol=1e-6)
    np.testing.assert_allclose(u1, u2, atol=1e-6)


def test_temperature_sharpens_and_flattens() -> None:
    cas = anchor_set([0.0, 1.0])
    logits = np.array([1.0, 0.0], np.float32).reshape(2, 1)
    hot = compute_maps(logits, cas, EngineSettings(temperature=100.0)).uncertainty[0]
    cold = compute_maps(logits, cas, EngineSettings(temperature=0.01)).uncertainty[0]
    assert hot == pytest.approx(0.5, abs=1e-3) and cold == pytest.approx(0.0, abs=1e-3)


def test_argmax_baseline() -> None:
    weights = np.array([[0.1, 0.7], [0.6, 0.2], [0.3, 0.1]], np.float32)  # (n=3, 2 patches)
    t, u = gcd.argmax_baseline(weights, np.array([0.0, 0.5, 1.0]))
    np.testing.assert_allclose(t, [0.5, 0.0])
    np.testing.assert_allclose(u, [0.4, 0.3], atol=1e-6)


def test_gaussian_baseline_recovers_a_gaussian_profile() -> None:
    positions = np.linspace(0, 1, 21)
    for mean, std in [(0.3, 0.1), (0.62, 0.05), (0.8, 0.15)]:
        logits = (-((positions - mean) ** 2) / (2 * std**2)).reshape(21, 1)
        t, u = gcd.gaussian_fit_baseline(gcd.softmax_weights(logits), positions)
        assert t[0] == pytest.approx(mean, abs=1e-3)
        assert u[0] == pytest.approx(std, abs=1e-3)


def test_gaussian_baseline_is_unimodal_where_gcd_is_not() -> None:
    # Two separated peaks: the GCD spreads over both, a single Gaussian cannot.
    positions = np.linspace(0, 1, 11)
    logits = np.full(11, -20.0)
    logits[[1, 9]] = 0.0
    logits[[0, 2, 8, 10]] = -1.0
    w = gcd.softmax_weights(logits.reshape(11, 1))
    _, u_gcd = gcd.mixture_mean_std(w, positions, np.zeros(11))
    _, u_fit = gcd.gaussian_fit_baseline(w, positions)
    assert u_gcd[0] > 0.35
    assert u_fit[0] < u_gcd[0]


def test_method_selection_and_shapes(rng: np.random.Generator) -> None:
    logits = rng.normal(0, 2, size=(13, 6, 7)).astype(np.float32)
    for method in Method:
        maps = compute_maps(logits, PAPER, EngineSettings(method=method))
        assert maps.traversability.shape == maps.uncertainty.shape == (6, 7)
        assert maps.traversability.dtype == maps.uncertainty.dtype == np.float32
        assert maps.weights.shape == (13, 6, 7)
    with pytest.raises(ValueError, match="do not match"):
        compute_maps(logits[:5], PAPER, EngineSettings())
    for method in Method:
        for bad in (np.nan, np.inf):
            one_bad_patch = logits.copy()
            one_bad_patch[4, 5, 6] = bad
            with pytest.raises(ValueError, match="NaN or infinity"):
                compute_maps(one_bad_patch, PAPER, EngineSettings(method=method))


def test_minus_infinity_is_a_weight_of_zero() -> None:
    cas = anchor_set([0.1, 0.6, 0.9])
    logits = np.array([-np.inf, 2.0, 2.0], np.float32).reshape(3, 1, 1)
    maps = compute_maps(logits, cas, EngineSettings())
    assert maps.weights[:, 0, 0].tolist() == [0.0, 0.5, 0.5]
    assert maps.traversability[0, 0] == pytest.approx(0.75, abs=1e-6)
    with pytest.raises(ValueError, match="NaN or infinity"):  # no finite logit: no distribution
        compute_maps(np.full((3, 1, 1), -np.inf, np.float32), cas, EngineSettings())


@pytest.mark.parametrize("shape", [(13, 1, 1), (13, 61, 67), (13, 352, 352), (5, 9000)])
@pytest.mark.parametrize("temperature", [1.0, 0.37])
def test_fused_blocks_equal_the_separate_passes(
    rng: np.random.Generator, shape: tuple[int, ...], temperature: float
) -> None:
    """The per-frame fused pass gives exactly the numbers of softmax, then mean and std, over whole arrays."""
    cas = anchor_set(sorted(rng.uniform(0, 1, shape[0]).tolist()), rng.uniform(0, 0.1, shape[0]).tolist())
    logits = rng.normal(0, 4, size=shape).astype(np.float32)
    weights, mean, std = gcd.softmax_mean_std(logits, cas.positions, cas.widths, temperature)
    scaled = logits / np.float32(temperature)
    exp = np.exp(scaled - scaled.max(axis=0))
    expected_weights = exp * np.reciprocal(exp.sum(axis=0))
    np.testing.assert_array_equal(weights, expected_weights)
    np.testing.assert_array_equal(gcd.softmax_weights(logits, temperature), expected_weights)
    moments = np.stack([np.asarray(cas.positions), np.asarray(cas.positions) ** 2 + np.asarray(cas.widths) ** 2])
    raw = np.tensordot(moments, expected_weights.astype(np.float64), axes=(1, 0))
    np.testing.assert_allclose(mean, np.clip(raw[0], 0, 1), rtol=0, atol=1e-7)
    np.testing.assert_allclose(std, np.sqrt(np.maximum(raw[1] - raw[0] ** 2, 0)), rtol=0, atol=1e-6)
    separate_mean, separate_std = gcd.mixture_mean_std(expected_weights, cas.positions, cas.widths)
    np.testing.assert_array_equal(mean, separate_mean)
    np.testing.assert_array_equal(std, separate_std)


def numeric_moments(w: np.ndarray, p: np.ndarray, s: np.ndarray) -> tuple[float, float, float, float]:
    x = np.linspace(-3, 4, 200001)
    density = sum(
        wk * np.exp(-0.5 * ((x - pk) / sk) ** 2) / (sk * np.sqrt(2 * np.pi)) for wk, pk, sk in zip(w, p, s, strict=True)
    )
    dx = x[1] - x[0]
    mean = np.sum(x * density) * dx
    var = np.sum((x - mean) ** 2 * density) * dx
    m3 = np.sum((x - mean) ** 3 * density) * dx
    m4 = np.sum((x - mean) ** 4 * density) * dx
    return mean, np.sqrt(var), m3 / var**1.5, m4 / var**2 - 3


def test_higher_moments_match_numerical_integration(rng: np.random.Generator) -> None:
    p = np.array([0.05, 0.3, 0.55, 0.9])
    s = np.array([0.04, 0.08, 0.03, 0.06])
    w = np.array([0.5, 0.1, 0.15, 0.25])
    stats = gcd.mixture_statistics(w.reshape(4, 1).astype(np.float32), p, s)
    mean, std, skew, kurt = numeric_moments(w, p, s)
    assert stats.mean[0] == pytest.approx(mean, abs=1e-5)
    assert stats.std[0] == pytest.approx(std, abs=1e-5)
    assert stats.skewness[0] == pytest.approx(skew, abs=1e-4)
    assert stats.excess_kurtosis[0] == pytest.approx(kurt, abs=1e-4)
    assert stats.entropy[0] == pytest.approx(-np.sum(w * np.log(w)), abs=1e-6)
    np.testing.assert_array_equal(stats.top_anchors[:, 0], [0, 3, 2])


def test_point_mass_statistics() -> None:
    w = np.zeros((3, 1), np.float32)
    w[1] = 1.0
    stats = gcd.mixture_statistics(w, [0.0, 0.5, 1.0], [0.0, 0.0, 0.0])
    assert stats.std[0] == 0 and stats.skewness[0] == 0 and stats.excess_kurtosis[0] == 0
    assert stats.entropy[0] == 0 and stats.modes[0] == 1


def test_modes_count_separated_peaks() -> None:
    w = np.zeros((13, 3), np.float32)
    w[6, 0] = 1.0  # grass only
    w[0, 1], w[6, 1] = 0.5, 0.5  # water and grass: the puddle's edge
    w[0, 2], w[6, 2], w[12, 2] = 0.3, 0.4, 0.3
    modes = gcd.count_modes(w, P, np.zeros(13))
    np.testing.assert_array_equal(modes, [1, 2, 3])


def test_density_integrates_to_one_inside_the_scale() -> None:
    w = np.full((3, 1), 1 / 3, np.float32)
    grid = gcd.density_grid(2001)
    density = gcd.mixture_density(w, [0.3, 0.5, 0.7], [0.05, 0.05, 0.05], grid)[0]
    assert np.trapezoid(density, grid) == pytest.approx(1.0, abs=1e-3)


def test_max_mixture_std(rng: np.random.Generator) -> None:
    assert gcd.max_mixture_std([0.02, 0.5, 1.0], [0, 0, 0]) == pytest.approx(0.49, abs=1e-9)
    positions = np.sort(rng.uniform(0, 1, 7))
    widths = rng.uniform(0, 0.3, 7)
    bound = gcd.max_mixture_std(positions, widths)
    weights = rng.dirichlet(np.full(7, 0.3), size=20000).T.astype(np.float32)
    _, stds = gcd.mixture_mean_std(weights, positions, widths)
    assert stds.max() <= bound + 1e-5
    assert stds.max() > bound * 0.9  # the bound is tight, not just an upper bound


finite_logits = arrays(
    np.float32, st.tuples(st.integers(2, 16), st.integers(1, 5)), elements=st.floats(-1e4, 1e4, width=32)
)


@settings(max_examples=200, deadline=None)
@given(logits=finite_logits, data=st.data())
def test_property_bounds(logits: np.ndarray, data: st.DataObject) -> None:
    n = logits.shape[0]
    positions = np.sort(np.asarray(data.draw(st.lists(st.floats(0, 1), min_size=n, max_size=n))))
    widths = np.asarray(data.draw(st.lists(st.floats(0, 0.5), min_size=n, max_size=n)))
    t, u = gcd.mixture_mean_std(gcd.softmax_weights(logits), positions, widths)
    assert np.all((t >= 0) & (t <= 1))
    assert np.all(u >= 0)
    assert np.all(u <= 0.5 + widths.max() + 1e-5)
