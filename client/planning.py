"""A* over a ground grid's risk layers: the cheapest 8-connected path between two cells (numpy, no torch).

Layers are 2-D arrays over the grid's cells (row i, column j), NaN where a cell was never observed:
``traversability`` (the GCD's mean T), ``cvar`` (its CVaR at some alpha) and ``p_below`` (P(T < tau)), as
gcdtrav.service.engine.risk computes them from a grid's anchor weights.

Cost model. The chosen measure gives each cell a risk r >= 0:
  mean      r = 1 - T
  cvar      r = 1 - CVaR_alpha        (risk-averse: a cell that may be water costs as water)
  p_below   r = P(T < tau)            (the chance the cell is worse than tau)
A step between neighbouring cells a and b costs  length * (1 + weight * (r_a + r_b) / 2),  length 1 for a
side step and sqrt(2) for a diagonal one (in cells): each cell counts for the half of the step inside it, so
a path costs the same both ways. Forbidden: unknown cells (``known`` False, or NaN in the cost layer) unless
``unknown`` gives them a risk; cells whose p_below exceeds ``lethal``; diagonal steps past a forbidden cell
at either side (no squeezing between two cells that touch only at a corner).

Search. A* with the octile distance times the cheapest passable cell's factor 1 + weight * r_min as the
heuristic: every step costs at least its length times that factor, so it is admissible and consistent and
the path found is a cheapest one. Costs and heuristic are computed with numpy; only the search loop is
Python, over flat lists of a grid padded with forbidden cells (no bounds checks in the loop).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from heapq import heappop, heappush
from typing import Literal

import numpy as np
from numpy.typing import NDArray

Cost = Literal["mean", "cvar", "p_below"]
Cell = tuple[int, int]

LAYER_OF_COST: dict[str, str] = {"mean": "traversability", "cvar": "cvar", "p_below": "p_below"}
# The worst cell of each layer along a path: the lowest T or CVaR, the highest chance of being below tau.
WORSE_IS_LOWER: dict[str, bool] = {"traversability": True, "cvar": True, "p_below": False}
DEFAULT_WEIGHT = 10.0
SQRT2 = math.sqrt(2.0)


class NoPathError(ValueError):
    """Start and goal are both passable but no passable path joins them."""


@dataclass(frozen=True)
class WorstCell:
    cell: Cell
    value: float


@dataclass(frozen=True)
class PlanResult:
    """A cheapest path, start and goal included, with what it costs and the worst it crosses."""

    cells: list[Cell]
    length_cells: float  # sum of step lengths: 1 per side step, sqrt(2) per diagonal one
    length_m: float  # length_cells * resolution
    cost: float  # sum of the step costs of the cost model
    worst: dict[str, WorstCell]  # per layer given, over the path's known cells (absent if it has none)


def _check_parameters(weight: float, unknown: float | None, lethal: float | None, resolution: float) -> None:
    if not (math.isfinite(weight) and weight >= 0):
        raise ValueError(f"weight must be finite and >= 0 (costs must not fall below the step length), got {weight}")
    if unknown is not None and not (math.isfinite(unknown) and unknown >= 0):
        raise ValueError(f"unknown must be None (forbidden) or a risk >= 0 for unknown cells, got {unknown}")
    if lethal is not None and not 0.0 <= lethal <= 1.0:
        raise ValueError(f"lethal must be None or a probability in [0, 1], got {lethal}")
    if not (math.isfinite(resolution) and resolution > 0):
        raise ValueError(f"resolution must be a positive cell size in metres, got {resolution}")


def _layer_arrays(
    layers: Mapping[str, NDArray[np.floating]], cost: str, known: NDArray[np.bool_] | None
) -> tuple[dict[str, NDArray[np.float64]], NDArray[np.bool_]]:
    """The layers as float64 arrays of one shape, and which cells are known."""
    if cost not in LAYER_OF_COST:
        raise ValueError(f"cost must be one of {sorted(LAYER_OF_COST)}, got {cost!r}")
    if LAYER_OF_COST[cost] not in layers:
        raise ValueError(f"cost {cost!r} needs the layer {LAYER_OF_COST[cost]!r}; layers given: {sorted(layers)}")
    arrays = {name: np.asarray(values, dtype=np.float64) for name, values in layers.items()}
    shape = arrays[LAYER_OF_COST[cost]].shape
    if len(shape) != 2 or 0 in shape:
        raise ValueError(f"layers must be non-empty 2-D grids (row, column), got shape {shape}")
    for name, values in arrays.items():
        if values.shape != shape:
            raise ValueError(f"layer {name!r} has shape {values.shape}, the cost layer {shape}")
    if known is None:
        return arrays, np.ones(shape, dtype=bool)
    known_cells = np.asarray(known, dtype=bool)
    if known_cells.shape != shape:
        raise ValueError(f"known has shape {known_cells.shape}, the layers {shape}")
    return arrays, known_cells


def _risk(values: NDArray[np.float64], cost: str) -> NDArray[np.float64]:
    risk = values if cost == "p_below" else 1.0 - values
    return np.maximum(risk, 0.0)  # a T or CVaR above 1 is no gain: costs stay >= the step length (admissible)


def _cell_factors(
    arrays: Mapping[str, NDArray[np.float64]],
    known: NDArray[np.bool_],
    cost: str,
    weight: float,
    unknown: float | None,
    lethal: float | None,
) -> tuple[NDArray[np.float64], dict[str, NDArray[np.bool_]]]:
    """Per cell 1 + weight * risk, inf where forbidden; and the forbidden cells by reason."""
    values = arrays[LAYER_OF_COST[cost]]
    unseen = ~known | np.isnan(values)
    factors = 1.0 + weight * _risk(np.where(unseen, 0.0, values), cost)
    factors[unseen] = math.inf if unknown is None else 1.0 + weight * unknown
    reasons = {"unknown": unseen if unknown is None else np.zeros_like(unseen)}
    if lethal is not None:
        if "p_below" not in arrays:
            raise ValueError("lethal needs the layer 'p_below'")
        with np.errstate(invalid="ignore"):  # NaN (unknown) is not lethal: unknown cells are handled above
            reasons["lethal"] = arrays["p_below"] > lethal
        factors[reasons["lethal"]] = math.inf
    return factors, reasons


def _check_endpoint(
    name: str, cell: Cell, factors: NDArray[np.float64], reasons: Mapping[str, NDArray[np.bool_]]
) -> None:
    rows, columns = factors.shape
    i, j = cell
    if not (0 <= i < rows and 0 <= j < columns):
        raise ValueError(f"{name} {cell} is outside the grid of {rows} x {columns} cells")
    if math.isinf(factors[i, j]):
        why = [reason for reason, cells in reasons.items() if cells[i, j]]
        raise ValueError(f"{name} {cell} is forbidden ({', '.join(why)})")


def _octile_heuristic(shape: tuple[int, int], goal: Cell, factor: float) -> NDArray[np.float64]:
    """factor * octile distance to goal, on the grid padded by one cell on each side."""
    rows, columns = np.indices((shape[0] + 2, shape[1] + 2))
    di, dj = np.abs(rows - 1 - goal[0]), np.abs(columns - 1 - goal[1])
    return factor * (np.abs(di - dj) + SQRT2 * np.minimum(di, dj))


def _moves(width: int) -> list[tuple[int, float, int, int]]:
    """(flat offset, half the step length, the two side cells a diagonal passes or 0) on a padded grid."""
    sides = [(-width, 0.5, 0, 0), (width, 0.5, 0, 0), (-1, 0.5, 0, 0), (1, 0.5, 0, 0)]
    diagonals = [(di * width + dj, 0.5 * SQRT2, di * width, dj) for di in (-1, 1) for dj in (-1, 1)]
    return sides + diagonals


def _search(factors: list[float], heuristic: list[float], width: int, start: int, goal: int) -> tuple[list[int], float]:
    """A* on the flat padded grid; the path's flat indices from start to goal, and its cost."""
    inf = math.inf
    best = [inf] * len(factors)
    parent = [-1] * len(factors)
    closed = bytearray(len(factors))
    moves = _moves(width)
    best[start] = 0.0
    frontier = [(heuristic[start], start)]
    while frontier:
        _, node = heappop(frontier)
        if node == goal:
            break
        if closed[node]:
            continue
        closed[node] = 1
        here, factor = best[node], factors[node]
        for offset, half_length, side_a, side_b in moves:
            neighbour = node + offset
            next_factor = factors[neighbour]
            if next_factor == inf or closed[neighbour]:
                continue
            if side_a and (factors[node + side_a] == inf or factors[node + side_b] == inf):
                continue
            cost = here + half_length * (factor + next_factor)
            if cost < best[neighbour]:
                best[neighbour] = cost
                parent[neighbour] = node
                heappush(frontier, (cost + heuristic[neighbour], neighbour))
    else:
        raise NoPathError("no passable path joins start and goal")
    path = [goal]
    while path[-1] != start:
        path.append(parent[path[-1]])
    return path[::-1], best[goal]


def _worst_cells(
    arrays: Mapping[str, NDArray[np.float64]], known: NDArray[np.bool_], cells: list[Cell]
) -> dict[str, WorstCell]:
    index = tuple(np.asarray(cells).T)
    worst = {}
    for name, lower_is_worse in WORSE_IS_LOWER.items():
        if name not in arrays:
            continue
        values = np.where(known[index], arrays[name][index], np.nan)
        if np.isnan(values).all():
            continue
        at = int(np.nanargmin(values) if lower_is_worse else np.nanargmax(values))
        worst[name] = WorstCell(cell=cells[at], value=float(values[at]))
    return worst


def plan(
    layers: Mapping[str, NDArray[np.floating]],
    start: Cell,
    goal: Cell,
    cost: Cost = "cvar",
    unknown: float | None = None,
    known: NDArray[np.bool_] | None = None,
    weight: float = DEFAULT_WEIGHT,
    lethal: float | None = None,
    resolution: float = 1.0,
) -> PlanResult:
    """The cheapest 8-connected path from start to goal (cells (row, column)) under the module's cost model.

    ``unknown``: None forbids unknown cells, a number is the risk they are given. ``lethal``: forbid cells
    with p_below above it (needs that layer). ``resolution``: metres per cell, for ``length_m``.
    Raises ValueError for a start or goal outside the grid or forbidden, NoPathError when none joins them.
    """
    _check_parameters(weight, unknown, lethal, resolution)
    arrays, known_cells = _layer_arrays(layers, cost, known)
    factors, reasons = _cell_factors(arrays, known_cells, cost, weight, unknown, lethal)
    start, goal = (int(start[0]), int(start[1])), (int(goal[0]), int(goal[1]))
    _check_endpoint("start", start, factors, reasons)
    _check_endpoint("goal", goal, factors, reasons)
    padded = np.pad(factors, 1, constant_values=math.inf)
    width = padded.shape[1]
    cheapest = float(factors[np.isfinite(factors)].min())
    heuristic = _octile_heuristic(factors.shape, goal, cheapest)
    flat_path, total = _search(
        padded.ravel().tolist(),
        heuristic.ravel().tolist(),
        width,
        (start[0] + 1) * width + start[1] + 1,
        (goal[0] + 1) * width + goal[1] + 1,
    )
    cells = [(index // width - 1, index % width - 1) for index in flat_path]
    steps = np.abs(np.diff(np.asarray(cells).reshape(-1, 2), axis=0)).sum(axis=1)
    length = float(np.sum(np.where(steps == 2, SQRT2, 1.0)))
    return PlanResult(
        cells=cells,
        length_cells=length,
        length_m=length * resolution,
        cost=total,
        worst=_worst_cells(arrays, known_cells, cells),
    )
