from __future__ import annotations

import heapq
import math

import numpy as np
import pytest
from gcdtrav.client.planning import NoPathError, plan


def uniform(rows: int, columns: int, t: float = 1.0) -> dict[str, np.ndarray]:
    grid = np.full((rows, columns), t)
    return {"traversability": grid, "cvar": grid.copy(), "p_below": np.zeros((rows, columns))}


def dijkstra_cost(factors: np.ndarray, start: tuple[int, int], goal: tuple[int, int]) -> float:
    """Reference: plain Dijkstra on the same cost model (inf factor = forbidden, no corner cutting)."""
    rows, columns = factors.shape
    best = {start: 0.0}
    frontier = [(0.0, start)]
    while frontier:
        cost, (i, j) = heapq.heappop(frontier)
        if (i, j) == goal:
            return cost
        if cost > best[(i, j)]:
            continue
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                a, b = i + di, j + dj
                if (di, dj) == (0, 0) or not (0 <= a < rows and 0 <= b < columns) or math.isinf(factors[a, b]):
                    continue
                if di and dj and (math.isinf(factors[a, j]) or math.isinf(factors[i, b])):
                    continue
                step = math.hypot(di, dj) * 0.5 * (factors[i, j] + factors[a, b])
                if cost + step < best.get((a, b), math.inf):
                    best[(a, b)] = cost + step
                    heapq.heappush(frontier, (cost + step, (a, b)))
    return math.inf


def test_straight_line_on_uniform_cost() -> None:
    result = plan(uniform(5, 10), (2, 0), (2, 9), cost="mean", resolution=0.1)
    assert result.cells == [(2, j) for j in range(10)]
    assert result.length_cells == 9 and result.length_m == pytest.approx(0.9) and result.cost == pytest.approx(9)
    diagonal = plan(uniform(6, 6, t=0.5), (0, 0), (5, 5), weight=2.0)
    assert diagonal.cells == [(k, k) for k in range(6)]
    assert diagonal.length_cells == pytest.approx(5 * math.sqrt(2))
    assert diagonal.cost == pytest.approx(5 * math.sqrt(2) * (1 + 2.0 * 0.5))


def test_detour_around_a_forbidden_wall() -> None:
    layers = uniform(10, 10)
    layers["cvar"][:9, 5] = np.nan  # unknown, so forbidden; the wall is open at the bottom row
    result = plan(layers, (0, 0), (0, 9))
    assert (9, 5) in result.cells
    assert not any(j == 5 and i < 9 for i, j in result.cells)
    assert result.length_cells > 9


def test_lethal_cells_are_forbidden() -> None:
    layers = uniform(10, 10)
    layers["p_below"][1:, 5] = 0.3
    assert (5, 5) in plan(layers, (5, 0), (5, 9)).cells
    result = plan(layers, (5, 0), (5, 9), lethal=0.2)
    assert (0, 5) in result.cells
    with pytest.raises(ValueError, match=r"goal \(5, 5\) is forbidden \(lethal\)"):
        plan(layers, (5, 0), (5, 5), lethal=0.2)


def test_no_corner_cutting_through_a_diagonal_wall() -> None:
    layers = uniform(4, 4)
    for k in range(4):
        layers["cvar"][k, 3 - k] = np.nan  # a diagonal wall: 8-connected it would leak
    with pytest.raises(NoPathError):
        plan(layers, (0, 0), (3, 3))


def test_no_path() -> None:
    layers = uniform(6, 6)
    layers["cvar"][:, 3] = np.nan
    with pytest.raises(NoPathError, match="no passable path"):
        plan(layers, (0, 0), (5, 5))


def test_unknown_cells_forbidden_or_at_a_set_risk() -> None:
    layers = uniform(7, 7)
    known = np.ones((7, 7), dtype=bool)
    known[:, 3] = False  # a band the robot has not seen, across every route
    with pytest.raises(NoPathError):
        plan(layers, (3, 0), (3, 6), known=known)
    result = plan(layers, (3, 0), (3, 6), known=known, unknown=0.5, weight=4.0)
    assert result.cells == [(3, j) for j in range(7)]
    assert result.cost == pytest.approx(5 + 2 * 0.5 * (1 + 4.0 * 0.5))  # two half steps in the unknown cell
    assert result.worst["cvar"].cell != (3, 3)  # unknown cells have no value to report
    with pytest.raises(ValueError, match=r"start \(3, 3\) is forbidden \(unknown\)"):
        plan(layers, (3, 3), (3, 6), known=known)


def test_one_cell_grid_start_is_goal() -> None:
    result = plan({"cvar": np.array([[0.4]])}, (0, 0), (0, 0))
    assert result.cells == [(0, 0)] and result.length_cells == 0 and result.cost == 0
    assert result.worst["cvar"].value == pytest.approx(0.4)


def puddle_scene() -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Firm ground (T = CVaR = 0.8) with a puddle band across the straight route, open at the top.

    The band's cells are half-and-half: their mean is middling (0.6) but their CVaR is water's (0.05).
    """
    layers = uniform(21, 30, t=0.8)
    band = np.zeros((21, 30), dtype=bool)
    band[5:, 12:18] = True
    layers["traversability"][band] = 0.6
    layers["cvar"][band] = 0.05
    layers["p_below"][band] = 0.4
    return layers, band


def test_puddle_mean_plan_crosses_cvar_plan_goes_round() -> None:
    layers, band = puddle_scene()
    by_mean = plan(layers, (12, 0), (12, 29), cost="mean")
    by_cvar = plan(layers, (12, 0), (12, 29), cost="cvar")
    assert any(band[cell] for cell in by_mean.cells)
    assert not any(band[cell] for cell in by_cvar.cells)
    assert by_mean.length_cells < by_cvar.length_cells
    assert by_mean.worst["cvar"].value == pytest.approx(0.05) and by_cvar.worst["cvar"].value == pytest.approx(0.8)
    assert by_mean.worst["p_below"].value == pytest.approx(0.4) and by_cvar.worst["p_below"].value == 0


@pytest.mark.parametrize("cost", ["mean", "cvar", "p_below"])
def test_cost_is_the_cheapest_as_dijkstra_finds_it(cost: str) -> None:
    rng = np.random.default_rng(7)
    t = rng.uniform(0.0, 1.0, (25, 25))
    layers = {"traversability": t, "cvar": t * rng.uniform(0.3, 1.0, t.shape), "p_below": rng.uniform(0, 1, t.shape)}
    layers["cvar"][rng.random(t.shape) < 0.15] = np.nan
    layers["traversability"][np.isnan(layers["cvar"])] = np.nan
    layers["p_below"][np.isnan(layers["cvar"])] = np.nan
    result = plan(layers, (0, 0), (24, 24), cost=cost, unknown=None, weight=3.0)  # type: ignore[arg-type]
    values = {"mean": 1 - layers["traversability"], "cvar": 1 - layers["cvar"], "p_below": layers["p_below"]}[cost]
    factors = np.where(np.isnan(values), math.inf, 1 + 3.0 * values)
    assert result.cost == pytest.approx(dijkstra_cost(factors, (0, 0), (24, 24)), rel=1e-12)
    steps = zip(result.cells, result.cells[1:], strict=False)
    assert all(max(abs(a - c), abs(b - d)) == 1 for (a, b), (c, d) in steps)


def test_bad_inputs_are_refused() -> None:
    layers = uniform(4, 5)
    with pytest.raises(ValueError, match=r"start \(4, 0\) is outside the grid of 4 x 5 cells"):
        plan(layers, (4, 0), (0, 0))
    with pytest.raises(ValueError, match=r"goal \(0, -1\) is outside"):
        plan(layers, (0, 0), (0, -1))
    with pytest.raises(ValueError, match="cost must be one of"):
        plan(layers, (0, 0), (1, 1), cost="median")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="needs the layer 'cvar'"):
        plan({"traversability": layers["traversability"]}, (0, 0), (1, 1))
    with pytest.raises(ValueError, match="lethal needs the layer 'p_below'"):
        plan({"cvar": layers["cvar"]}, (0, 0), (1, 1), lethal=0.5)
    with pytest.raises(ValueError, match="layer 'p_below' has shape"):
        plan({"cvar": layers["cvar"], "p_below": np.zeros((3, 3))}, (0, 0), (1, 1))
    with pytest.raises(ValueError, match="weight must be finite and >= 0"):
        plan(layers, (0, 0), (1, 1), weight=-1.0)
    with pytest.raises(ValueError, match="2-D grids"):
        plan({"cvar": np.zeros(5)}, (0, 0), (1, 1))
