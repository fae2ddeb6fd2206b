"""The speed layer: per cell, the fraction of the robot's maximum speed the grid vouches for, and that fraction
as Nav2's speed filter reads it (docs/grid.md, "Speed from uncertainty").

    slow     = max(ramp(U; u_full, u_floor), ramp(P(T < tau); p_below_full, p_below_floor))   in [0, 1]
    fraction = 1 - (1 - floor) * slow                                                         in [floor, 1]

``ramp(v; a, b)`` is 0 at or below a, 1 at or above b, linear between. A novel cell (match score below
``min_match``) and a known cell whose U or P(T < tau) is not a number take the floor; an unknown cell (never
observed, or expired) the floor or full speed, as ``unknown`` says. Then each cell takes the slowest fraction
within ``lead_m`` of it (a min filter over a disc): SpeedFilter on Jazzy and Kilted reads only the robot's own
cell, so slow ground must reach out by the robot's braking distance for it to arrive there slow.

Nav2's SpeedFilter (nav2_costmap_2d/plugins/costmap_filters/speed_filter.cpp) reads a mask value v of 1..100
as ``base + multiplier * v`` percent of the maximum speed (type 1; base 0 and multiplier 1 here), 0 as no limit,
and -1 (unknown) as an error that keeps whatever limit it had: so the mask never holds -1, and full speed is 0.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from gcdtrav.schemas.ros_nav import HIGHEST_PERCENT, LOWEST_PERCENT, NO_LIMIT
from gcdtrav.schemas.settings import GridSpeedSettings
from gcdtrav.service.grid.layers import GridLayers
from numpy.typing import NDArray


def ramp(values: NDArray[np.floating], start: float, end: float) -> NDArray[np.float32]:
    """0 at or below ``start``, 1 at or above ``end`` (> start), linear between; NaN stays NaN."""
    return np.asarray(np.clip((values - start) / (end - start), 0.0, 1.0), np.float32)


def speed_fractions(layers: GridLayers, settings: GridSpeedSettings, resolution_m: float) -> NDArray[np.float32]:
    """Every cell's fraction of maximum speed, in [floor, 1] (rows i = y, columns j = x, as the grid, whose
    cells are ``resolution_m`` wide)."""
    with np.errstate(invalid="ignore"):  # NaN where unknown: set below
        slow = np.fmax(
            ramp(layers.uncertainty, settings.u_full, settings.u_floor),
            ramp(layers.p_below, settings.p_below_full, settings.p_below_floor),
        )
        novel = layers.match < settings.min_match
    known = layers.known
    # a known cell without a number for U or P(T < tau) (fmax gives NaN only when both are) or novel: the floor
    slow = np.where(known & (novel | ~np.isfinite(slow)), 1.0, slow)
    fractions = (1.0 - (1.0 - settings.floor) * slow).astype(np.float32)
    fractions[~known] = settings.floor if settings.unknown == "floor" else 1.0
    return lead_in(fractions, settings.lead_m, resolution_m)


def lead_in(fractions: NDArray[np.float32], lead_m: float, resolution_m: float) -> NDArray[np.float32]:
    """Each cell's slowest fraction within ``lead_m`` (OpenCV's elliptic disc of that radius in cells; the grid's
    rim taken as it is); unchanged below one cell."""
    radius = math.floor(lead_m / resolution_m + 1e-9)
    if radius < 1:
        return fractions
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    return np.asarray(cv2.erode(fractions, disc, borderType=cv2.BORDER_REPLICATE), np.float32)


def limit_percent(fraction: float) -> float:
    """nav2_msgs/SpeedLimit.speed_limit (percentage true) for a fraction: 0 (no limit) at full speed."""
    percent = float(np.clip(round(fraction * 100), LOWEST_PERCENT, HIGHEST_PERCENT))
    return float(NO_LIMIT) if percent >= HIGHEST_PERCENT else percent


def safe_fraction(settings: GridSpeedSettings) -> float:
    """The fraction a stale, drained or stopped grid leaves in force everywhere: the floor (docs/grid.md, "Speed
    from uncertainty": a robot whose perception went quiet slows, it does not speed up)."""
    return settings.floor


def fraction_at(
    fractions: NDArray[np.floating], origin: tuple[float, float], resolution: float, x: float, y: float
) -> float | None:
    """The fraction in the cell holding (x, y) (the grid's frame); None outside the grid."""
    j, i = int(np.floor((x - origin[0]) / resolution)), int(np.floor((y - origin[1]) / resolution))
    rows, columns = fractions.shape
    if not (0 <= i < rows and 0 <= j < columns):
        return None
    return float(fractions[i, j])
