"""The ground grid's layers a planner reads, one Foxglove channel pair each: a ``foxglove.Grid`` for the 3D
panel (the value and its colour per cell) and a top-down picture with the same colours and a legend, like the
image maps. And the Nav2 costmap, which the service publishes as a ``nav_msgs/OccupancyGrid`` (CDR), read
here without ROS."""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
from gcdtrav.client.client import Grid as GridMaps
from gcdtrav.client.view import pictures
from gcdtrav.client.view.pictures import MapKind
from gcdtrav.schemas.grid_layers import GRID_LAYERS
from gcdtrav.schemas.messages import GridHeader
from gcdtrav.schemas.ros_nav import read_occupancy_grid
from numpy.typing import NDArray

# (channel name, colour scale) of every layer the table draws: T, U, CVaR, P(T < tau), match and age; layers a
# grid lacks (older writers) have no channel.
LAYERS: tuple[tuple[str, MapKind], ...] = tuple(
    (layer.name, cast(MapKind, layer.scale)) for layer in GRID_LAYERS if layer.scale is not None
)
COSTMAP = "costmap"  # its channel name, scale "cost"
LAYER_CELL_BYTES = 8  # the value (float32, NaN = unknown) and its colour as red, green, blue, alpha (uint8)
ROBOT_COLOUR = (255, 255, 255)


def layer_values(grid: GridMaps) -> dict[str, tuple[MapKind, NDArray[np.float32]]]:
    """The grid's layers by channel name, those it has; NaN where unknown (age: never observed)."""
    found: dict[str, tuple[MapKind, NDArray[np.float32]]] = {}
    for name, kind in LAYERS:
        values = grid.layers.get(name)
        if values is not None:
            found[name] = (kind, np.asarray(values, np.float32))
    return found


def layer_title(kind: MapKind, header: GridHeader) -> str | None:
    """The legend's title with the level it was computed at, e.g. 'CVaR 0.10'."""
    if kind == "cvar" and header.alpha is not None:
        return f"CVaR {header.alpha:.2f}"
    if kind == "p_below" and header.tau is not None:
        return f"P(T<{header.tau:.2f})"
    return None


def layer_cells(values: NDArray[np.floating], kind: MapKind) -> bytes:
    """The cells packed row by row (row i = y), LAYER_CELL_BYTES each: the value and its colour (alpha 0 for
    unknown cells, so they are transparent in the 3D panel's "RGBA (separate fields)" mode)."""
    values = np.asarray(values, np.float32)
    cells = np.zeros(values.shape, np.dtype([("value", "<f4"), ("rgba", "u1", (4,))]))
    cells["value"] = values
    known = np.isfinite(values)
    cells["rgba"][..., :3] = pictures.colour_map(values, kind)
    cells["rgba"][..., 3] = np.where(known, 255, 0)
    return cells.tobytes()


def layer_picture(values: NDArray[np.floating], kind: MapKind, header: GridHeader) -> NDArray[np.uint8]:
    """The layer seen from above, x to the right and y up (row 0 at the bottom), unknown cells grey, the
    robot as a white dot with a heading tick, and the legend at the right."""
    picture = pictures.map_with_legend(np.asarray(values)[::-1], kind, title=layer_title(kind, header))
    if header.robot is not None:
        cells = values.shape[0]
        pixels = picture.shape[0] / cells  # the map is enlarged by whole multiples
        x, y, yaw = header.robot
        column = (x - header.origin[0]) / header.resolution
        row = cells - (y - header.origin[1]) / header.resolution  # flipped
        if 0 <= column < cells and 0 <= row < cells:
            centre = (round(column * pixels), round(row * pixels))
            radius = max(3, round(pixels))
            tip = (round(centre[0] + 3 * radius * np.cos(yaw)), round(centre[1] - 3 * radius * np.sin(yaw)))
            cv2.circle(picture, centre, radius, ROBOT_COLOUR, -1, cv2.LINE_AA)
            cv2.line(picture, centre, tip, ROBOT_COLOUR, 2, cv2.LINE_AA)
    return picture


@dataclass(frozen=True)
class OccupancyGrid:
    """A nav_msgs/OccupancyGrid: int8 cells (row i = y), -1 unknown; ``origin`` the corner of cell (0, 0)."""

    stamp: float
    frame_id: str
    resolution: float
    origin: tuple[float, float]
    data: NDArray[np.int8]

    def values(self) -> NDArray[np.float32]:
        """The cells as floats, NaN where unknown (-1)."""
        return np.where(self.data < 0, np.nan, self.data.astype(np.float32)).astype(np.float32)


def decode_occupancy_grid(payload: bytes) -> OccupancyGrid:
    """A nav_msgs/msg/OccupancyGrid from its CDR (schemas/ros_nav.py); RosNavError (a ValueError) for anything
    else."""
    geometry, cells = read_occupancy_grid(payload)
    return OccupancyGrid(geometry.stamp, geometry.frame_id, geometry.resolution, geometry.origin, cells)


def costmap_header(costmap: OccupancyGrid) -> GridHeader:
    """A GridHeader placing the costmap's picture (no robot, no layers' levels)."""
    return GridHeader(
        source="", seq=0, stamp=costmap.stamp, frame_id=costmap.frame_id, origin=costmap.origin,
        resolution=costmap.resolution, cells=costmap.data.shape[1], anchor_set_version="", resets=0,
        known_cells=int((costmap.data >= 0).sum()), instance="",
    )  # fmt: skip
