"""The speed layer (service/grid/speed.py) at its edges: U = 0 and U at its maximum, P(T < tau), unknown and NaN
cells, novel ground, the floor and floor = 1 (no slowing); the mask Nav2 reads (never -1, 0 = no limit)."""

from __future__ import annotations

import numpy as np
import pytest
from gcdtrav.schemas.ros_nav import speed_mask_values as mask_values
from gcdtrav.schemas.settings import GridSettings, GridSpeedSettings
from gcdtrav.service.grid import speed
from gcdtrav.service.grid.layers import GridLayers
from gcdtrav.service.grid.speed import fraction_at, lead_in, limit_percent
from pydantic import ValidationError

U_MAX = 0.5  # the largest std of a mixture over [0, 1] with zero widths (half at 0, half at 1)


def speed_fractions(layers: GridLayers, settings: GridSpeedSettings) -> np.ndarray:
    """The fractions of cells 1 m wide without a lead-in (lead_m below one cell): each cell on its own."""
    return speed.speed_fractions(layers, settings, resolution_m=1.0)


def cells(u: list[float], p_below: list[float] | None = None, match: list[float] | None = None,
          count: list[int] | None = None) -> GridLayers:  # fmt: skip
    """One row of cells with these U (NaN allowed), P(T < tau), match scores and counts."""
    n = len(u)

    def row(values: list[float] | None, default: float) -> np.ndarray:
        return np.array([values if values is not None else [default] * n], np.float32)

    counts = np.array([count if count is not None else [1] * n], np.int64)
    unknown = counts == 0
    uncertainty = np.where(unknown, np.nan, row(u, 0.0)).astype(np.float32)
    p = np.where(unknown, np.nan, row(p_below, 0.0)).astype(np.float32)
    m = np.where(unknown, np.nan, row(match, 1.0)).astype(np.float32)
    t = np.full((1, n), 0.8, np.float32)
    return GridLayers(t, uncertainty, t, p, m, counts, np.zeros((1, n)), p, 0.1, 0.3, 0.3)


def test_u_zero_is_full_speed_and_u_at_its_maximum_the_floor() -> None:
    settings = GridSpeedSettings(floor=0.3, u_full=0.1, u_floor=0.2)
    fractions = speed_fractions(cells([0.0, 0.1, 0.15, 0.2, U_MAX]), settings)
    np.testing.assert_allclose(fractions[0], [1.0, 1.0, 0.65, 0.3, 0.3], atol=1e-6)


def test_p_below_slows_alone_and_the_larger_of_the_two_wins() -> None:
    settings = GridSpeedSettings(floor=0.2, p_below_full=0.1, p_below_floor=0.5)
    fractions = speed_fractions(cells([0.0, 0.0, 0.0, 0.15], p_below=[0.0, 0.3, 1.0, 0.3]), settings)
    # p 0.3: half way (0.6); U 0.15 is half way too; p 1.0: the floor
    np.testing.assert_allclose(fractions[0], [1.0, 0.6, 0.2, 0.6], atol=1e-6)


@pytest.mark.parametrize(("unknown", "expected"), [("floor", 0.3), ("full", 1.0)])
def test_unknown_cells_take_the_configured_value(unknown: str, expected: float) -> None:
    settings = GridSpeedSettings(floor=0.3, unknown=unknown)
    fractions = speed_fractions(cells([0.0, 0.0], count=[1, 0]), settings)
    np.testing.assert_allclose(fractions[0], [1.0, expected])


def test_a_known_cell_without_numbers_takes_the_floor_not_full_speed() -> None:
    settings = GridSpeedSettings(floor=0.4, unknown="full")
    fractions = speed_fractions(cells([np.nan, np.nan, 0.0], p_below=[np.nan, 0.0, np.nan]), settings)
    # both NaN: the floor; one NaN: the other decides
    np.testing.assert_allclose(fractions[0], [0.4, 1.0, 1.0])
    assert np.isfinite(fractions).all()


def test_novel_ground_takes_the_floor_and_min_match_zero_never_does() -> None:
    layers = cells([0.0, 0.0, 0.0], match=[0.0, 0.19, 0.2])
    np.testing.assert_allclose(speed_fractions(layers, GridSpeedSettings(floor=0.3, min_match=0.2))[0], [0.3, 0.3, 1])
    np.testing.assert_allclose(speed_fractions(layers, GridSpeedSettings(floor=0.3))[0], [1.0, 1.0, 1.0])


def test_floor_one_never_slows_and_its_mask_is_no_limit_everywhere() -> None:
    settings = GridSpeedSettings(floor=1.0)
    layers = cells([0.0, U_MAX, np.nan, 0.3], p_below=[1.0, 1.0, 1.0, 0.0], match=[0.0] * 4, count=[1, 1, 1, 0])
    fractions = speed_fractions(layers, settings)
    np.testing.assert_array_equal(fractions, 1.0)
    np.testing.assert_array_equal(mask_values(fractions), 0)


def test_the_mask_is_percent_1_to_100_with_0_for_full_speed_and_never_unknown() -> None:
    fractions = np.array([[1.0, 0.999, 0.995, 0.3, 0.01, 0.004, 0.0, np.nan]], np.float32)
    np.testing.assert_array_equal(mask_values(fractions), [[0, 0, 0, 30, 1, 1, 1, 1]])
    assert mask_values(fractions).dtype == np.int8
    assert [limit_percent(f) for f in (1.0, 0.3, 0.001)] == [0.0, 30.0, 1.0]


def test_the_fraction_at_a_point_and_off_the_grid() -> None:
    fractions = np.array([[0.1, 0.2], [0.3, 0.4]], np.float32)  # rows y, columns x
    assert fraction_at(fractions, (-1.0, -1.0), 1.0, 0.5, -0.5) == pytest.approx(0.2)
    assert fraction_at(fractions, (-1.0, -1.0), 1.0, -0.5, 0.5) == pytest.approx(0.3)
    assert fraction_at(fractions, (-1.0, -1.0), 1.0, 1.0, 0.0) is None
    assert fraction_at(fractions, (-1.0, -1.0), 1.0, 0.0, -1.01) is None


def test_speed_settings_are_strict_and_their_ramps_rise() -> None:
    with pytest.raises(ValidationError, match="u_full"):
        GridSpeedSettings(u_full=0.2, u_floor=0.2)
    with pytest.raises(ValidationError, match="p_below_full"):
        GridSpeedSettings(p_below_full=0.6, p_below_floor=0.5)
    with pytest.raises(ValidationError):
        GridSpeedSettings(floor=0.0)  # a 0 % mask value would read as "no limit"
    with pytest.raises(ValidationError):
        GridSpeedSettings(rate_hz=0.0)
    with pytest.raises(ValidationError, match=r"extra|not permitted"):
        GridSpeedSettings.model_validate({"flor": 0.3})
    grid = GridSettings.model_validate({"source": "cam", "camera_info_key": "k", "speed": {"floor": 0.5}})
    assert grid.speed is not None and grid.speed.floor == 0.5
    assert GridSettings(source="cam", camera_info_key="k").speed is None


def test_slow_ground_reaches_out_lead_m_and_no_further() -> None:
    fractions = np.ones((9, 9), np.float32)
    fractions[4, 4] = 0.3
    spread = lead_in(fractions, lead_m=0.2, resolution_m=0.1)  # two cells
    assert spread[4, 2] == spread[4, 6] == spread[2, 4] == pytest.approx(0.3) and spread[4, 1] == 1.0
    assert spread[3, 3] == pytest.approx(0.3) and spread[2, 2] == 1.0  # a disc, not a square
    np.testing.assert_array_equal(lead_in(fractions, lead_m=0.09, resolution_m=0.1), fractions)  # under a cell
    np.testing.assert_array_equal(lead_in(fractions, lead_m=0.0, resolution_m=0.1), fractions)
    edge = np.ones((3, 3), np.float32)
    edge[0, 0] = 0.5
    assert lead_in(edge, 0.1, 0.1)[0, 1] == 0.5 and lead_in(edge, 0.1, 0.1)[2, 2] == 1.0  # the rim as any cell
    layers = cells([0.0, 0.0, 0.0, U_MAX, 0.0])
    slowed = speed.speed_fractions(layers, GridSpeedSettings(floor=0.3, lead_m=1.0), resolution_m=1.0)
    np.testing.assert_allclose(slowed[0], [1.0, 1.0, 0.3, 0.3, 0.3])


def test_the_lowest_floor_is_one_percent_never_no_limit() -> None:
    settings = GridSpeedSettings(floor=0.01)
    fractions = speed_fractions(cells([U_MAX, 0.0], count=[1, 0]), settings)
    np.testing.assert_allclose(fractions[0], [0.01, 0.01], atol=1e-6)
    np.testing.assert_array_equal(mask_values(fractions), [[1, 1]])  # 1 %, not 0 (which Nav2 reads as no limit)
    assert limit_percent(float(fractions[0, 0])) == 1.0


def test_the_settings_edges_are_accepted_and_beyond_them_refused() -> None:
    edges = GridSpeedSettings(floor=1.0, rate_hz=10.0, lead_m=5.0, min_match=1.0, u_full=0.0, u_floor=1.0)
    assert (edges.rate_hz, edges.lead_m) == (10.0, 5.0)
    for beyond in ({"rate_hz": 10.01}, {"lead_m": 5.01}, {"lead_m": -0.1}, {"floor": 1.01}, {"stale_s": 0.0},
                   {"unknown": "nan"}, {"u_floor": 1.01}):  # fmt: skip
        with pytest.raises(ValidationError):
            GridSpeedSettings.model_validate(beyond)
