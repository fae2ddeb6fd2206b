"""Cell and path queries of a ground grid, in metres in the grid's frame, with risk levels."""

from __future__ import annotations

import numpy as np
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.messages import ContextDistribution, PathReply
from gcdtrav.schemas.settings import RiskSettings
from gcdtrav.service.runtime.errors import QueryError
from gcdtrav.service.runtime.grids.state import SourceGrid
from gcdtrav.service.runtime.queries import (
    RISK_PARAMETERS,
    RiskLevels,
    distribution_of,
    parameter_pairs,
    parse_number,
    risk_levels,
    strict_parameters,
    with_risk,
)

CELL_FORMS = (
    "x=..;y=.. (metres, grid frame), or path=x0,y0;x1,y1;..., and optionally alpha=.. (0 < alpha <= 1), tau=.. "
    "(0 <= tau <= 1)"
)
MAX_PATH_POINTS = 256


def answer(
    sources: dict[str, SourceGrid], source: str, raw_parameters: str, risk: RiskSettings | None = None
) -> ContextDistribution | PathReply:
    """A cell's or a path's distributions, over the anchor set the grid's weights were fused with."""
    grid = sources.get(source)
    if grid is None:
        raise QueryError(f"no grid for source '{source}' (grids: {sorted(sources)})")
    params, levels = _without_risk_levels(raw_parameters.strip(), risk or RiskSettings())
    with grid.lock:
        anchors = grid.grid.anchors
        if anchors is None:
            raise QueryError(f"the grid of '{source}' has no frame yet")
        if params.startswith("path="):
            return path_reply(grid, _points(params[len("path=") :]), anchors, levels)
        values = strict_parameters(parameter_pairs(params), CELL_FORMS)
        if set(values) != {"x", "y"}:
            raise QueryError(f"give {CELL_FORMS}")
        x, y = parse_number(values["x"], "x"), parse_number(values["y"], "y")
        i, j = (int(v) for v in grid.grid.index_of(np.array(x), np.array(y)))
        n = grid.grid.spec.cells
        if not (0 <= i < n and 0 <= j < n):
            lo, hi = (
                grid.grid.origin,
                (
                    grid.grid.origin[0] + n * grid.grid.spec.resolution_m,
                    grid.grid.origin[1] + n * grid.grid.spec.resolution_m,
                ),
            )
            raise QueryError(f"({x:g}, {y:g}) is outside the grid [{lo[0]:g}, {hi[0]:g}) x [{lo[1]:g}, {hi[1]:g})")
        cell = cell_reply(grid, i, j, anchors, levels)
        if cell is None:
            raise QueryError(f"cell ({x:g}, {y:g}) is unknown: never observed")
        return cell


def cell_reply(grid: SourceGrid, i: int, j: int, anchors: AnchorSet, levels: RiskLevels) -> ContextDistribution | None:
    weights = grid.grid.cell_weights(i, j)
    if weights is None:
        return None
    weights = weights / weights.sum()
    reply = distribution_of(
        weights,
        anchors,
        grid.config.source,
        None,  # a cell fuses many frames: no one frame's seq
        grid.grid.stamp or 0.0,
        grid.frame_id(),
    )
    match = grid.grid.cell_match(i, j)  # the grid's match layer: a cell answers with it, as a patch does
    return with_risk(reply, weights, anchors, levels, match).model_copy(
        update={
            "cell": (i, j),
            "cell_xy": grid.grid.centre_of(i, j),
            "observations": int(grid.grid.count[i, j]),
            "grid_updates": grid.seq,
        }
    )


def path_reply(
    grid: SourceGrid, points: list[tuple[float, float]], anchors: AnchorSet, levels: RiskLevels
) -> PathReply:
    cells, unknown = [], 0
    for i, j in grid.grid.path_cells(points):
        cell = cell_reply(grid, i, j, anchors, levels)
        if cell is None:
            unknown += 1
        else:
            cells.append(cell)
    below = [cell.p_below or 0.0 for cell in cells]
    return PathReply(
        source=grid.config.source,
        stamp=grid.grid.stamp or 0.0,
        anchor_set_version=anchors.version,
        points=points,
        cells=cells,
        unknown_cells=unknown,
        lowest_t=min(range(len(cells)), key=lambda k: cells[k].mean) if cells else None,
        highest_u=max(range(len(cells)), key=lambda k: cells[k].std) if cells else None,
        lowest_cvar=min(range(len(cells)), key=lambda k: cells[k].cvar or 0.0) if cells else None,
        p_any_below=float(1 - np.prod(1 - np.asarray(below, np.float64))) if cells else None,
        alpha=levels.alpha,
        tau=levels.tau,
    )


def _without_risk_levels(params: str, defaults: RiskSettings) -> tuple[str, RiskLevels]:
    """The cell or path parameters without alpha and tau, and the levels they give: a path's points are
    ';'-separated too, so alpha=.. and tau=.. are taken out wherever they stand."""
    risky = [(name, value) for name, value in parameter_pairs(params) if name in RISK_PARAMETERS]
    rest = ";".join(part for part in params.split(";") if part.split("=", 1)[0] not in RISK_PARAMETERS)
    levels = strict_parameters(risky, CELL_FORMS)
    return rest, risk_levels(levels, defaults)


def _points(text: str) -> list[tuple[float, float]]:
    points = []
    for part in text.split(";"):
        if not part.strip():
            continue
        coordinates = part.split(",")
        if len(coordinates) != 2:
            raise QueryError(f"path point '{part}' must be x,y in metres")
        points.append((parse_number(coordinates[0], "x"), parse_number(coordinates[1], "y")))
    if not 2 <= len(points) <= MAX_PATH_POINTS:
        raise QueryError(f"a path needs 2 to {MAX_PATH_POINTS} points x,y separated by ';', got {len(points)}")
    return points
