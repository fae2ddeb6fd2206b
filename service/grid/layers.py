"""A grid's layers for planners: T, U and the risk measures per cell, the fused match score, counts and ages,
and the Nav2 costmap graded from them (docs/grid.md, "Layers" and "Nav2 costmap").

Every float layer is NaN where the cell is unknown (never observed, or expired); ``age`` is NaN only where
the cell was never observed: an expired cell keeps its age.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from gcdtrav.schemas.grid_layers import COUNT, GRID_LAYERS
from gcdtrav.service.engine import risk
from gcdtrav.service.grid.fusion import GroundGrid
from numpy.typing import NDArray

# nav_msgs/OccupancyGrid values of the costmap, as Nav2's static layer reads them (static_layer.cpp).
UNKNOWN_COST = -1  # unknown_cost_value 255: NO_INFORMATION with track_unknown_space, else FREE_SPACE
LETHAL_COST = 100  # >= lethal_cost_threshold (100): LETHAL_OBSTACLE
LOWEST_COST = 1  # CVaR 1: the best ground still costs a little, 0 (free) is never sent
# CVaR 0: the top of the graded range. Not 99: Nav2 after Kilted (Rolling since December 2025) reads 99 as
# INSCRIBED_INFLATED_OBSTACLE (inscribed_obstacle_cost_value, default 99).
HIGHEST_COST = 98


@dataclass(frozen=True)
class GridLayers:
    """Every cell's layers (rows i = y, columns j = x, as the grid), at the risk levels alpha and tau: one
    attribute per row of the grid layers' table (schemas/grid_layers.py), and p_lethal for the costmap."""

    traversability: NDArray[np.float32]
    uncertainty: NDArray[np.float32]
    cvar: NDArray[np.float32]  # CVaR_alpha of T: the mean of its worst alpha
    p_below: NDArray[np.float32]  # P(T < tau)
    match: NDArray[np.float32]  # fused match score, 0 (no concept fits) to 1
    count: NDArray[np.int64]  # pixels fused (0: unknown)
    age: NDArray[np.float64]  # seconds from the last observation to the grid's stamp; NaN: never observed
    p_lethal: NDArray[np.float32]  # P(T < lethal_tau), for the costmap (p_below itself when lethal_tau = tau)
    alpha: float
    tau: float
    lethal_tau: float
    speed: NDArray[np.float32] | None = None  # fraction of maximum speed (grid/speed.py); None: no speed layer

    @property
    def known(self) -> NDArray[np.bool_]:
        return self.count > 0

    def values(self) -> dict[str, NDArray[Any]]:
        """Every layer of the table (schemas/grid_layers.py) by name, as the GridMessage encodes it."""
        found = {layer.name: getattr(self, layer.name) for layer in GRID_LAYERS}
        return {name: values for name, values in found.items() if values is not None}

    def float_layers(self) -> dict[str, NDArray[np.float32]]:
        """Every layer as float32 by name, in the table's order, unknown NaN: a GridMap's layers."""
        values = self.values() | {COUNT: np.where(self.known, self.count, np.nan)}
        return {name: np.asarray(value, np.float32) for name, value in values.items()}


def grid_layers(
    grid: GroundGrid,
    positions: NDArray[np.floating],
    widths: NDArray[np.floating],
    alpha: float,
    tau: float,
    lethal_tau: float | None = None,
) -> GridLayers:
    """The layers of a grid over the anchors it was fused with; the risk measures on known cells only (the
    weight sums, normalised per cell by risk.py, are the cells' distributions)."""
    t, u, count = grid.layers(positions, widths)
    known = count > 0
    lethal_tau = tau if lethal_tau is None else lethal_tau
    cvar, p_below, p_lethal = (np.full(known.shape, np.nan, np.float32) for _ in range(3))
    if known.any():
        sums = grid.weight_sums[:, known]
        measures = risk.risk_measures(sums, positions, widths, alpha, tau)
        cvar[known], p_below[known] = measures.cvar, measures.p_below
        p_lethal[known] = measures.p_below if lethal_tau == tau else risk.p_below(sums, positions, widths, lethal_tau)
    return GridLayers(t, u, cvar, p_below, grid.match(), count, grid.age(), p_lethal, alpha, tau, lethal_tau)


def nav2_costs(layers: GridLayers, lethal_probability: float, min_match: float) -> NDArray[np.int8]:
    """The costmap's nav_msgs/OccupancyGrid values (rows i = y, columns j = x).

    Graded 1 + round(97 (1 - CVaR_alpha)): 1 (CVaR 1) to 98 (CVaR 0). Lethal (100) where P(T < lethal_tau)
    > lethal_probability. Unknown (-1) where never observed or expired, or the match score is below min_match.
    """
    cvar = np.clip(np.nan_to_num(layers.cvar, nan=0.0), 0.0, 1.0)
    costs = (LOWEST_COST + np.round((HIGHEST_COST - LOWEST_COST) * (1.0 - cvar))).astype(np.int8)
    with np.errstate(invalid="ignore"):  # NaN is unknown, set last
        costs[layers.p_lethal > lethal_probability] = LETHAL_COST
        novel = layers.match < min_match
    costs[~layers.known | novel | ~np.isfinite(layers.cvar)] = UNKNOWN_COST
    return costs
