"""nav2_msgs' CostmapFilterInfo and SpeedLimit, and Costmap with its CostmapMetaData, for rosbags: not among
its built-in types, registered from their .msg text, copied verbatim (comments included; they are not part of a
type). The first two from Nav2's Kilted release 1.4.2 (github.com/ros-navigation/navigation2, tag 1.4.2, commit
3478badb7e2802c9ff1f805fb5493dc1d0792a5a, nav2_msgs/msg/; the same on the jazzy branch); Costmap.msg and
CostmapMetaData.msg from navigation2's main branch (commits c2c6b230 and 26d583f3, read 2026-11-28), the type
the collision monitor's costmap source reads (nav2_collision_monitor/src/costmap.cpp). nav2_msgs is licensed
Apache-2.0 (its package.xml), Copyright the Nav2 contributors. rosbags computes their RIHS01 type hashes from
them like any other type's; tests/service/ros/test_nav2_msgs.py checks those against ROS 2's own generator
(rosidl_generator_type_description).
"""

from __future__ import annotations

from typing import Any

COSTMAP_FILTER_INFO = "nav2_msgs/msg/CostmapFilterInfo"
SPEED_LIMIT = "nav2_msgs/msg/SpeedLimit"
COSTMAP = "nav2_msgs/msg/Costmap"
COSTMAP_META_DATA = "nav2_msgs/msg/CostmapMetaData"

COSTMAP_FILTER_INFO_MSG = """\
std_msgs/Header header
# Type of plugin used (keepout filter, speed limit in m/s, speed limit in percent, etc...)
# 0: keepout/lanes filter
# 1: speed limit filter in % of maximum speed
# 2: speed limit filter in absolute values (m/s)
uint8 type
# Name of filter mask topic
string filter_mask_topic
# Multiplier base offset and multiplier coefficient for conversion of OccGrid.
# Used to convert OccupancyGrid data values to filter space values.
# data -> into some other number space:
# space = data * multiplier + base
float32 base
float32 multiplier
"""
SPEED_LIMIT_MSG = """\
std_msgs/Header header
# Setting speed limit in percentage if true or in absolute values in false case
bool percentage
# Maximum allowed speed (in percent of maximum robot speed or in m/s depending
# on "percentage" value). When no-limit it is set to 0.0
float64 speed_limit
"""
COSTMAP_META_DATA_MSG = """\
# This hold basic information about the characteristics of the Costmap

# The time at which the static map was loaded
builtin_interfaces/Time map_load_time

# The time of the last update to costmap
builtin_interfaces/Time update_time

# The corresponding layer name
string layer

# The map resolution [m/cell]
float32 resolution

# Number of cells in the horizontal direction
uint32 size_x

# Number of cells in the vertical direction
uint32 size_y

# The origin of the costmap [m, m, rad].
# This is the real-world pose of the cell (0,0) in the map.
geometry_msgs/Pose origin
"""
COSTMAP_MSG = """\
# This represents a 2-D grid map, in which each cell has an associated cost

std_msgs/Header header

# MetaData for the map
CostmapMetaData metadata

# The cost data, in row-major order, starting with (0,0).
uint8[] data
"""
# dependencies first: rosbags resolves a field's type among those registered
MESSAGES = {
    COSTMAP_FILTER_INFO: COSTMAP_FILTER_INFO_MSG,
    SPEED_LIMIT: SPEED_LIMIT_MSG,
    COSTMAP_META_DATA: COSTMAP_META_DATA_MSG,
    COSTMAP: COSTMAP_MSG,
}


def register_types(store: Any) -> None:
    """Add nav2_msgs' messages above to a rosbags typestore (std_msgs, geometry_msgs are built in)."""
    from rosbags.typesys import get_types_from_msg

    for name, text in MESSAGES.items():
        store.register(get_types_from_msg(text, name))
