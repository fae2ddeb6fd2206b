"""What the viewer draws, with numpy and OpenCV only: T and U as colour-mapped images with a legend, and the
ground grid as Foxglove Grid cells (T, U, count and T's colours)."""

from __future__ import annotations

from typing import Literal

import cv2
import numpy as np
from gcdtrav.client.client import Grid
from gcdtrav.schemas.images import UNCERTAINTY_VMAX, colorize_traversability, colorize_uncertainty
from numpy.typing import NDArray

MapKind = Literal["T", "U"]
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


def colour_map(values: NDArray[np.floating], kind: MapKind) -> NDArray[np.uint8]:
    """RGB colours of T (red = untraversable .. green = ideal) or U (dark = certain .. bright = ambiguous)."""
    return colorize_traversability(values) if kind == "T" else colorize_uncertainty(values)


def map_with_legend(
    values: NDArray[np.floating], kind: MapKind, image_size: tuple[int, int] | None = None
) -> NDArray[np.uint8]:
    """The colour-mapped map at the camera's aspect (``image_size`` = (width, height); else the map's own), at
    least MIN_HEIGHT rows, with a colour bar and its scale at the right."""
    width, height = picture_size(values.shape, image_size)
    picture = cv2.resize(colour_map(values, kind), (width, height), interpolation=cv2.INTER_NEAREST)
    return np.concatenate([picture, legend(kind, height)], axis=1)


def picture_size(map_shape: tuple[int, ...], image_size: tuple[int, int] | None) -> tuple[int, int]:
    """(width, height) to draw a map of ``map_shape`` (rows, columns): whole multiples of its rows up to
    MIN_HEIGHT (cells stay sharp), and the image's aspect, since the maps cover the image whatever their shape."""
    rows, columns = map_shape[:2]
    height = rows * max(1, -(-MIN_HEIGHT // rows))
    if image_size is None or min(image_size) <= 0:
        return columns * height // rows, height
    image_width, image_height = image_size
    return max(1, round(height * image_width / image_height)), height


def legend(kind: MapKind, height: int) -> NDArray[np.uint8]:
    """A vertical colour bar, top = the scale's end, with the title and three ticks."""
    panel = np.full((height, LEGEND_WIDTH, 3), BACKGROUND, np.uint8)
    top, bottom, left, right = 30, height - 12, 8, 28
    top_value = 1.0 if kind == "T" else UNCERTAINTY_VMAX
    ramp = np.linspace(top_value, 0.0, bottom - top, dtype=np.float32)[:, None].repeat(right - left, axis=1)
    panel[top:bottom, left:right] = colour_map(ramp, kind)
    title = "T" if kind == "T" else "U (std)"
    cv2.putText(panel, title, (left, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, TEXT, 1, cv2.LINE_AA)
    for fraction in (0.0, 0.5, 1.0):
        y = round(top + fraction * (bottom - top - 1))
        label = f"{top_value * (1 - fraction):.2f}"
        cv2.line(panel, (right, y), (right + 4, y), TEXT, 1)
        cv2.putText(panel, label, (right + 7, y + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, TEXT, 1, cv2.LINE_AA)
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
