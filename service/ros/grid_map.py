"""grid_map_msgs/msg/GridMap CDR from a gcdtrav grid's layers, and back (docs/grid.md, "GridMap").

grid_map_msgs is not among rosbags' built-in types: cdr.typestore() registers its two messages from their .msg
text (grid_map_msgs.py).

Index conventions. gcdtrav: cell (i, j) is row i along y, column j along x, the origin (ox, oy) the corner of
cell (0, 0), N x N cells of side r. grid_map (grid_map_core/src/GridMapMath.cpp): the map's position is its
CENTRE; with start index (0, 0), index (a, b) is the cell whose centre is
  x = px + length_x / 2 - r / 2 - a r,   y = py + length_y / 2 - r / 2 - b r,
so index (0, 0) is the max-x, max-y corner and a runs along -x, b along -y. A layer is a column-major Eigen
matrix of size (cells along x, cells along y) sent as a Float32MultiArray with dims "column_index" (size
cells along y, stride all cells) and "row_index" (size cells along x, stride cells along x): element (a, b)
is data[b * size_x + a] (grid_map_ros/GridMapMsgHelpers.hpp). Hence a = N - 1 - j, b = N - 1 - i and
data[b * N + a] = grid[N - 1 - b, N - 1 - a]: the data is the gcdtrav grid flipped along both axes, in
row-major order. The position is (ox + N r / 2, oy + N r / 2); no circular buffer (start indices 0).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gcdtrav.schemas.messages import GridHeader
from gcdtrav.service.ros import cdr
from gcdtrav.service.ros.grid_map_msgs import GRID_MAP, GRID_MAP_INFO
from numpy.typing import NDArray

COLUMN_INDEX, ROW_INDEX = "column_index", "row_index"  # grid_map's storageIndexNames


def to_grid_map_order(layer: NDArray[Any]) -> NDArray[np.float32]:
    """A gcdtrav layer (row i = y, column j = x) as grid_map's data array (see the module's docstring)."""
    return np.ascontiguousarray(np.asarray(layer, np.float32)[::-1, ::-1]).ravel()


def grid_map_cdr(header: GridHeader, layers: dict[str, NDArray[np.floating]], basic_layers: list[str]) -> bytes:
    """A GridMap with the layers (NaN where unknown, grid_map's "no data"), in the grid's frame."""
    store = cdr.typestore()
    types = store.types
    n, r = header.cells, header.resolution
    length = n * r
    centre = types["geometry_msgs/msg/Point"](x=header.origin[0] + length / 2, y=header.origin[1] + length / 2, z=0.0)
    pose = types["geometry_msgs/msg/Pose"](
        position=centre, orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
    )
    info = types[GRID_MAP_INFO](resolution=r, length_x=length, length_y=length, pose=pose)
    dimension = types["std_msgs/msg/MultiArrayDimension"]
    layout = types["std_msgs/msg/MultiArrayLayout"](
        dim=[dimension(label=COLUMN_INDEX, size=n, stride=n * n), dimension(label=ROW_INDEX, size=n, stride=n)],
        data_offset=0,
    )
    array = types["std_msgs/msg/Float32MultiArray"]
    message = types[GRID_MAP](
        header=cdr.make_header(header.stamp, header.frame_id),
        info=info,
        layers=list(layers),
        basic_layers=basic_layers,
        data=[array(layout=layout, data=to_grid_map_order(values)) for values in layers.values()],
        outer_start_index=0,
        inner_start_index=0,
    )
    return bytes(store.serialize_cdr(message, GRID_MAP))
