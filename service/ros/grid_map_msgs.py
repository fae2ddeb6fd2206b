"""grid_map_msgs' message definitions, for rosbags: not among its built-in types, registered from their .msg
text (ANYbotics/grid_map, grid_map_msgs/msg, identical on the humble, jazzy and rolling branches; comments left
out, they are not part of a type). rosbags computes their RIHS01 type hash from them like any other type's.
"""

from __future__ import annotations

from typing import Any

GRID_MAP = "grid_map_msgs/msg/GridMap"
GRID_MAP_INFO = "grid_map_msgs/msg/GridMapInfo"

GRID_MAP_INFO_MSG = """\
float64 resolution
float64 length_x
float64 length_y
geometry_msgs/Pose pose
"""
GRID_MAP_MSG = """\
std_msgs/Header header
GridMapInfo info
string[] layers
string[] basic_layers
std_msgs/Float32MultiArray[] data
uint16 outer_start_index
uint16 inner_start_index
"""


def register_types(store: Any) -> None:
    """Add grid_map_msgs' GridMapInfo and GridMap to a rosbags typestore (its other types are built in)."""
    from rosbags.typesys import get_types_from_msg

    types = {**get_types_from_msg(GRID_MAP_INFO_MSG, GRID_MAP_INFO), **get_types_from_msg(GRID_MAP_MSG, GRID_MAP)}
    store.register(types)
