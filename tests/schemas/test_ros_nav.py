"""schemas/ros_nav.py, the robot side's nav_msgs CDR, against ROS 2's own serialiser (the ROS 2 wheels) and
rosbags' (the service extra): byte for byte where it writes, field for field where it reads."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from gcdtrav.schemas.ros_nav import (
    RosNavError,
    occupancy_grid_cdr,
    occupancy_grid_geometry,
    odometry_pose,
    path_points,
    split_stamp,
)

CELLS = np.arange(-1, 14, dtype=np.int8).reshape(3, 5)


@pytest.mark.parametrize("frame_id", ["", "odom", "a_frame_of_odd_length"])
def test_an_occupancy_grid_is_what_rosbags_writes(frame_id: str) -> None:
    pytest.importorskip("rosbags")
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    message = store.types["nav_msgs/msg/OccupancyGrid"]
    header = store.types["std_msgs/msg/Header"]
    time = store.types["builtin_interfaces/msg/Time"]
    meta = store.types["nav_msgs/msg/MapMetaData"]
    pose = store.types["geometry_msgs/msg/Pose"]
    point = store.types["geometry_msgs/msg/Point"]
    quaternion = store.types["geometry_msgs/msg/Quaternion"]
    expected = store.serialize_cdr(
        message(
            header=header(stamp=time(sec=12, nanosec=345), frame_id=frame_id),
            info=meta(
                map_load_time=time(sec=12, nanosec=345),
                resolution=np.float32(0.25),
                width=5,
                height=3,
                origin=pose(position=point(x=-1.5, y=2.0, z=0.0), orientation=quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
            ),
            data=CELLS.ravel(),
        ),
        "nav_msgs/msg/OccupancyGrid",
    )
    written = occupancy_grid_cdr((12, 345), frame_id, 0.25, (-1.5, 2.0), CELLS)
    assert written == bytes(expected)
    geometry = occupancy_grid_geometry(written)
    assert (geometry.frame_id, geometry.resolution, geometry.width, geometry.height) == (frame_id, 0.25, 5, 3)
    assert geometry.origin == (-1.5, 2.0) and geometry.stamp == pytest.approx(12.000000345)


def test_an_occupancy_grid_and_odometry_as_ros2_serialises_them() -> None:
    from real_components import require_rclpy

    require_rclpy()
    from nav_msgs.msg import OccupancyGrid, Odometry
    from rclpy.serialization import deserialize_message, serialize_message

    grid = deserialize_message(occupancy_grid_cdr((7, 8), "odom", 1.0, (3.0, -4.0), CELLS), OccupancyGrid)
    assert (grid.header.stamp.sec, grid.header.stamp.nanosec, grid.header.frame_id) == (7, 8, "odom")
    assert (grid.info.width, grid.info.height, grid.info.resolution) == (5, 3, 1.0)
    assert (grid.info.origin.position.x, grid.info.origin.position.y, grid.info.origin.orientation.w) == (3, -4, 1)
    assert list(grid.data) == CELLS.ravel().tolist()

    odometry = Odometry()
    odometry.header.stamp.sec, odometry.header.stamp.nanosec, odometry.header.frame_id = 5, 6, "odom"
    odometry.child_frame_id = "base_link"
    odometry.pose.pose.position.x, odometry.pose.pose.position.y = 1.25, -2.5
    yaw = 0.7
    odometry.pose.pose.orientation.z, odometry.pose.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    odometry.pose.covariance[0] = 9.0
    pose = odometry_pose(serialize_message(odometry))
    assert (pose.frame_id, pose.x, pose.y) == ("odom", 1.25, -2.5)
    assert pose.yaw == pytest.approx(yaw) and pose.stamp == pytest.approx(5.000000006)
    assert occupancy_grid_geometry(serialize_message(grid)).frame_id == "odom"


@pytest.mark.parametrize("payload", [b"", b"\x00\x01\x00\x00", b"\x00\x01\x00\x00" + b"\xff" * 40, b"\x82\xa1x\x01"])
def test_what_is_not_a_grid_or_odometry_is_refused(payload: bytes) -> None:
    with pytest.raises(RosNavError):
        occupancy_grid_geometry(payload)
    with pytest.raises(RosNavError):
        odometry_pose(payload)


def test_a_grid_whose_cells_do_not_match_its_size_is_refused() -> None:
    written = occupancy_grid_cdr((1, 0), "odom", 1.0, (0.0, 0.0), CELLS)
    wider = written.replace(struct.pack("<fII", 1.0, 5, 3), struct.pack("<fII", 1.0, 6, 3))
    assert wider != written
    with pytest.raises(RosNavError, match="6x3 cells"):
        occupancy_grid_geometry(wider)


@pytest.mark.parametrize(("stamp", "split"), [(0.0, (0, 0)), (1.5, (1, 500_000_000)), (2.9999999999, (2, 999_999_999))])
def test_split_stamp(stamp: float, split: tuple[int, int]) -> None:
    assert split_stamp(stamp) == split


def rosbags_path(frame_id: str, points: list[tuple[float, float]], pose_frame: str) -> bytes:
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types = store.types
    header, time = types["std_msgs/msg/Header"], types["builtin_interfaces/msg/Time"]
    pose_stamped, pose = types["geometry_msgs/msg/PoseStamped"], types["geometry_msgs/msg/Pose"]
    point, quaternion = types["geometry_msgs/msg/Point"], types["geometry_msgs/msg/Quaternion"]
    poses = [
        pose_stamped(
            header=header(stamp=time(sec=3, nanosec=4), frame_id=pose_frame),
            pose=pose(position=point(x=x, y=y, z=0.5), orientation=quaternion(x=0.0, y=0.0, z=0.6, w=0.8)),
        )
        for x, y in points
    ]
    path = types["nav_msgs/msg/Path"](header=header(stamp=time(sec=12, nanosec=345), frame_id=frame_id), poses=poses)
    return bytes(store.serialize_cdr(path, "nav_msgs/msg/Path"))


@pytest.mark.parametrize(
    ("frame_id", "points", "pose_frame"),
    [("odom", [(1.0, -2.0), (1.5, -2.25), (3.0, 4.0)], ""), ("map", [], "map"), ("", [(0.0, 0.0)], "odd_frame")],
)
def test_a_path_reads_as_rosbags_writes_it(frame_id: str, points: list[tuple[float, float]], pose_frame: str) -> None:
    pytest.importorskip("rosbags")
    assert path_points(rosbags_path(frame_id, points, pose_frame)) == (frame_id, pytest.approx(12.000000345), points)


def test_a_path_as_ros2_serialises_it() -> None:
    from real_components import require_rclpy

    require_rclpy()
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Path
    from rclpy.serialization import serialize_message

    path = Path()
    path.header.stamp.sec, path.header.frame_id = 9, "odom"
    for x, y in [(0.25, 0.5), (-7.0, 8.125)]:
        stamped = PoseStamped()
        stamped.header.frame_id = "odom"
        stamped.pose.position.x, stamped.pose.position.y = x, y
        path.poses.append(stamped)
    assert path_points(serialize_message(path)) == ("odom", 9.0, [(0.25, 0.5), (-7.0, 8.125)])


def test_a_path_that_is_not_one_is_refused() -> None:
    pytest.importorskip("rosbags")
    written = rosbags_path("odom", [(1.0, 2.0), (3.0, 4.0)], "odom")
    for payload in (b"", written[:-9], b"\x82\xa1x\x01"):
        with pytest.raises(RosNavError, match="nav_msgs/msg/Path"):
            path_points(payload)
    count_at = written.index(struct.pack("<I", 2), 4 + 8 + 4 + 5)  # after the header: the poses' count
    with pytest.raises(RosNavError, match="4000000000 poses"):
        path_points(written[:count_at] + struct.pack("<I", 4_000_000_000) + written[count_at + 4 :])
    not_finite = written.replace(struct.pack("<d", 3.0), struct.pack("<d", math.inf))
    with pytest.raises(RosNavError, match="not finite"):
        path_points(not_finite)
