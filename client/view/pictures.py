"""What the viewer draws, with numpy and OpenCV only: T, U and the grid's layers as colour-mapped images with a
legend, and the ground grid as Foxglove Grid cells (T, U, count and T's colours)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from gcdtrav.client.client import Grid
from gcdtrav.schemas.images import UNCERTAINTY_VMAX, colorize_traversability, colorize_uncertainty
from numpy.typing import NDArray

MapKind = Literal["T", "U", "cvar", "p_below", "match", "cost", "age", "speed"]
MIN_HEIGHT = 256  # small maps are enlarged (nearest neighbour) so the legend's text stays readable
LEGEND_WIDTH = 84
BACKGROUND = (40, 40, 40)
TEXT = (235, 235, 235)

# One grid cell in the Grid message: T and U (float32, NaN = never observed), the observation count and
# T's colour as red/green/blue/alpha, which Foxglove's 3D panel shows with "RGBA (separate fields)".
GRID_FIELDS: tuple[tuple[str, int, str], ...] = (
    ("T", 0, "float32"),
    ("U", 4, "float32"),
    ("count", 8, "uint32"),
    ("red", 12, "uint8"),
    ("green", 13, "uint8"),
    ("blue", 14, "uint8"),
    ("alpha", 15, "uint8"),
)
GRID_CELL_BYTES = 16
_CELL = np.dtype(
    {"names": [f[0] for f in GRID_FIELDS], "formats": ["<f4", "<f4", "<u4", "u1", "u1", "u1", "u1"],
     "offsets": [f[1] for f in GRID_FIELDS], "itemsize": GRID_CELL_BYTES}
)  # fmt: skip


@dataclass(frozen=True)
class Scale:
    """How one kind of map is coloured and labelled: its legend runs from ``low`` (bottom) to ``high`` (top)."""

    title: str
    high: float
    colours: Callable[[NDArray[np.floating]], NDArray[np.uint8]]
    low: float = 0.0
    top_label: str = ""  # instead of the top value, e.g. "100 lethal"


def _risk_colours(p: NDArray[np.floating]) -> NDArray[np.uint8]:
    """P(T < tau): green 0 (safe) .. red 1, T's colours reversed."""
    return colorize_traversability(1.0 - np.asarray(p, np.float32))


def _match_colours(match: NDArray[np.floating]) -> NDArray[np.uint8]:
    """Dark = no anchor describes the ground .. yellow = well described (viridis)."""
    index = np.round(np.clip(np.asarray(match, np.float32), 0, 1) * 255).astype(np.uint8)
    colours = np.asarray(cv2.cvtColor(cv2.applyColorMap(index, cv2.COLORMAP_VIRIDIS), cv2.COLOR_BGR2RGB), np.uint8)
    return colours


LETHAL_COST, LOWEST_COST, HIGHEST_COST = 100, 1, 98  # the Nav2 costmap's values (docs/grid.md)
LETHAL_COLOUR = (200, 0, 200)  # magenta: outside the graded scale


def _cost_colours(cost: NDArray[np.floating]) -> NDArray[np.uint8]:
    """Nav2 costs: 1 (green, CVaR 1) .. 98 (red, CVaR 0) as T's colours of the CVaR they grade; 100 magenta."""
    cost = np.asarray(cost, np.float32)
    colours = colorize_traversability(1.0 - (cost - LOWEST_COST) / (HIGHEST_COST - LOWEST_COST))
    colours[cost >= LETHAL_COST - 0.5] = LETHAL_COLOUR
    return colours


AGE_SCALE_S = 60.0  # the age layer's colours end here: older is as dark


def _age_colours(age: NDArray[np.floating]) -> NDArray[np.uint8]:
    return colorize_uncertainty(np.asarray(age, np.float32), AGE_SCALE_S)


SCALES: dict[str, Scale] = {
    "T": Scale("T", 1.0, colorize_traversability),
    "U": Scale("U (std)", UNCERTAINTY_VMAX, colorize_uncertainty),
    "cvar": Scale("CVaR", 1.0, colorize_traversability),
    "p_below": Scale("P(T<tau)", 1.0, _risk_colours),
    "match": Scale("match", 1.0, _match_colours),
    "cost": Scale("Nav2 cost", LETHAL_COST, _cost_colours, top_label="100 lethal"),
    "age": Scale("age (s)", AGE_SCALE_S, _age_colours),
    # the speed layer: red = the floor .. green = full speed (T's colours: slow where the grid is unsure)
    "speed": Scale("speed (of max)", 1.0, colorize_traversability),
}
UNKNOWN_COLOUR = (70, 70, 70)  # cells never observed, in the grid's pictures


def colour_map(values: NDArray[np.floating], kind: MapKind) -> NDArray[np.uint8]:
    """RGB colours of a map of ``kind``: T (red = untraversable .. green = ideal), U (dark = certain .. bright
    = ambiguous), and the grid's layers (SCALES); NaN (unknown) is UNKNOWN_COLOUR."""
    values = np.asarray(values, np.float32)
    unknown = ~np.isfinite(values)
    colours = SCALES[kind].colours(np.where(unknown, 0.0, values))
    colours[unknown] = UNKNOWN_COLOUR
    return colours


def map_with_legend(
    values: NDArray[np.floating],
    kind: MapKind,
    image_size: tuple[int, int] | None = None,
    title: str | None = None,
) -> NDArray[np.uint8]:
    """The colour-mapped map at the camera's aspect (``image_size`` = (width, height); else the map's own), at
    least MIN_HEIGHT rows, with a colour bar and its scale at the right (titled ``title`` or the scale's)."""
    width, height = picture_size(values.shape, image_size)
    picture = cv2.resize(colour_map(values, kind), (width, height), interpolation=cv2.INTER_NEAREST)
    return np.concatenate([picture, legend(kind, height, title)], axis=1)


def picture_size(map_shape: tuple[int, ...], image_size: tuple[int, int] | None) -> tuple[int, int]:
    """(width, height) to draw a map of ``map_shape`` (rows, columns): whole multiples of its rows up to
    MIN_HEIGHT (cells stay sharp), and the image's aspect, since the maps cover the image whatever their shape."""
    rows, columns = map_shape[:2]
    height = rows * max(1, -(-MIN_HEIGHT // rows))
    if image_size is None or min(image_size) <= 0:
        return columns * height // rows, height
    image_width, image_height = image_size
    return max(1, round(height * image_width / image_height)), height


def legend(kind: MapKind, height: int, title: str | None = None) -> NDArray[np.uint8]:
    """A vertical colour bar, top = the scale's end, with the title and three ticks."""
    scale = SCALES[kind]
    panel = np.full((height, LEGEND_WIDTH, 3), BACKGROUND, np.uint8)
    top, bottom, left, right = 30, height - 12, 8, 28
    ramp = np.linspace(scale.high, scale.low, bottom - top, dtype=np.float32)[:, None].repeat(right - left, axis=1)
    panel[top:bottom, left:right] = colour_map(ramp, kind)
    cv2.putText(panel, title or scale.title, (4, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.42, TEXT, 1, cv2.LINE_AA)
    whole = scale.high >= 10
    for fraction in (0.0, 0.5, 1.0):
        y = round(top + fraction * (bottom - top - 1))
        value = scale.high - fraction * (scale.high - scale.low)
        label = f"{value:.0f}" if whole else f"{value:.2f}"
        if fraction == 0.0 and scale.top_label:
            label = scale.top_label
        cv2.line(panel, (right, y), (right + 4, y), TEXT, 1)
        cv2.putText(panel, label, (right + 7, y + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35, TEXT, 1, cv2.LINE_AA)
    return panel


def png(rgb: NDArray[np.uint8]) -> bytes:
    ok, buffer = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError("PNG encoding failed")
    return buffer.tobytes()


def jpeg(rgb: NDArray[np.uint8], quality: int = 85) -> bytes:
    ok, buffer = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buffer.tobytes()


def grid_cells(grid: Grid) -> bytes:
    """The grid's cells packed row by row (row i = y), GRID_CELL_BYTES each, as GRID_FIELDS describes."""
    cells = np.zeros(grid.count.shape, _CELL)
    cells["T"], cells["U"] = grid.traversability, grid.uncertainty
    cells["count"] = np.clip(grid.count, 0, np.iinfo(np.uint32).max)
    known = grid.count > 0
    colours = colorize_traversability(np.nan_to_num(grid.traversability))
    cells["red"], cells["green"], cells["blue"] = colours[..., 0], colours[..., 1], colours[..., 2]
    cells["alpha"] = np.where(known, 255, 0)
    return cells.tobytes()
