"""The ROS facts the service and the relay share, in CDR with numpy only (the relay has no ROS typestore, and
both must agree): a ``nav_msgs/msg/OccupancyGrid`` written (the relay's safe speed mask) and its geometry read
back; Nav2's speed filter info (``CostmapFilterInfo``); a stamped message's header restamped; the one rule from
a ``nav_msgs/msg/Odometry`` to a pose (a grid's pose stream, the safe mask's centre) and its velocity (the
outcomes); a ``geometry_msgs/msg/Twist`` or ``TwistStamped``, a ``std_msgs/msg/Bool`` and a ``nav_msgs/msg/Path``.

Plain CDR, little-endian, as schemas/ros_image.py reads it: a 4-byte encapsulation header, then each field
aligned to its size from the end of that header. Checked against ROS 2's own serialiser
(tests/schemas/test_ros_nav.py, with the ROS 2 wheels) and rosbags'.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np
from gcdtrav.schemas.experience import Odometry2D, Twist2D
from gcdtrav.schemas.messages import MessageError, Pose2D
from gcdtrav.schemas.ros_image import _Malformed, _Reader
from numpy.typing import NDArray

OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
ODOMETRY = "nav_msgs/msg/Odometry"
PATH = "nav_msgs/msg/Path"
TWIST, TWIST_STAMPED, BOOL = "geometry_msgs/msg/Twist", "geometry_msgs/msg/TwistStamped", "std_msgs/msg/Bool"
# A PoseStamped's least CDR: a stamp (8 bytes), an empty frame id (4 + 1, then 3 of padding) and 7 doubles
POSE_STAMPED_BYTES = 8 + 8 + 7 * 8
COVARIANCE = 36  # doubles of a PoseWithCovariance's or TwistWithCovariance's covariance
ENCAPSULATION = b"\x00\x01\x00\x00"  # CDR, little-endian


COSTMAP_FILTER_INFO = "nav2_msgs/msg/CostmapFilterInfo"
SPEED_LIMIT = "nav2_msgs/msg/SpeedLimit"
SPEED_FILTER_PERCENT = 1  # CostmapFilterInfo.type: a mask value v is v percent of the maximum speed (filter_values.hpp)
NO_LIMIT = 0  # a speed mask value (and SpeedLimit.speed_limit) Nav2 reads as "no limit"
LOWEST_PERCENT, HIGHEST_PERCENT = 1, 100
DEFAULT_ODOMETRY_FRAME = "odom"  # an Odometry whose header names no frame: REP 105's odometry frame


class RosNavError(MessageError):
    """Not the ROS message's CDR, or a value in it not usable."""


@dataclass(frozen=True)
class GridGeometry:
    """Where an OccupancyGrid lies: its frame, cell size, cells and the corner of cell (0, 0) (yaw 0)."""

    frame_id: str
    resolution: float
    width: int
    height: int
    origin: tuple[float, float]
    stamp: float  # the header's


class _Writer:
    def __init__(self) -> None:
        self.data = bytearray(ENCAPSULATION)

    def number(self, code: str, value: float) -> None:
        size = struct.calcsize(code)
        self.data += bytes(-(len(self.data) - 4) % size)
        self.data += struct.pack("<" + code, value)

    def string(self, text: str) -> None:
        raw = text.encode("utf-8") + b"\x00"
        self.number("I", len(raw))
        self.data += raw

    def octets(self, raw: bytes) -> None:
        self.number("I", len(raw))
        self.data += raw

    def done(self) -> bytes:
        return bytes(self.data)  # unpadded at the end, as ROS 2's serialiser and rosbags' write it


def seconds(sec_nanosec: tuple[int, int]) -> float:
    return sec_nanosec[0] + sec_nanosec[1] * 1e-9


def split_stamp(stamp: float) -> tuple[int, int]:
    """A float stamp as (sec, nanosec), nanosec in [0, 1e9)."""
    sec = math.floor(stamp)
    return sec, min(round((stamp - sec) * 1e9), 999_999_999)


def occupancy_grid_cdr(
    stamp: tuple[int, int],
    frame_id: str,
    resolution: float,
    origin: tuple[float, float],
    cells: NDArray[np.int8],
) -> bytes:
    """An OccupancyGrid of ``cells`` (rows i = y, columns j = x), cell (0, 0)'s corner at ``origin``, yaw 0."""
    height, width = cells.shape
    writer = _Writer()
    writer.number("i", stamp[0])
    writer.number("I", stamp[1])
    writer.string(frame_id)
    writer.number("i", stamp[0])  # info.map_load_time: made now, as the header says
    writer.number("I", stamp[1])
    writer.number("f", resolution)
    writer.number("I", width)
    writer.number("I", height)
    for value in (origin[0], origin[1], 0.0, 0.0, 0.0, 0.0, 1.0):  # position, then the identity quaternion
        writer.number("d", value)
    writer.octets(np.ascontiguousarray(cells, np.int8).tobytes())
    return writer.done()


def speed_mask_values(fractions: NDArray[np.floating]) -> NDArray[np.int8]:
    """The speed filter mask's nav_msgs/OccupancyGrid values for fractions of maximum speed: percent, 1..100,
    and 0 (no limit) at full speed; never -1 (SpeedFilter keeps its old limit on it); not a number: the lowest.
    The service's grids and the relay's safe mask both write these."""
    percent = np.clip(np.round(np.nan_to_num(fractions, nan=0.0) * 100), LOWEST_PERCENT, HIGHEST_PERCENT)
    return np.where(percent >= HIGHEST_PERCENT, NO_LIMIT, percent).astype(np.int8)


def costmap_filter_info_cdr(frame_id: str, mask_topic: str) -> bytes:
    """nav2_msgs/CostmapFilterInfo of a speed mask in percent (type 1, base 0, multiplier 1: a mask value v is v
    percent). Stamped 0: the same bytes for the same mask topic, so the info is put once, not with every mask
    (each new info makes Nav2's SpeedFilter drop its mask and subscribe afresh)."""
    writer = _Writer()
    writer.number("i", 0)
    writer.number("I", 0)
    writer.string(frame_id)
    writer.number("B", SPEED_FILTER_PERCENT)
    writer.string(mask_topic)
    writer.number("f", 0.0)  # base
    writer.number("f", 1.0)  # multiplier
    return writer.done()


def speed_limit_cdr(stamp: tuple[int, int], frame_id: str, percent: float) -> bytes:
    """nav2_msgs/SpeedLimit in percent of the maximum speed (0: no limit): the relay's safe limit, which a
    controller that takes the SpeedLimit directly (no SpeedFilter) reads as the safe mask's floor."""
    writer = _Writer()
    writer.number("i", stamp[0])
    writer.number("I", stamp[1])
    writer.string(frame_id)
    writer.number("B", 1)  # percentage
    writer.number("d", float(percent))
    return writer.done()


def restamped(payload: bytes, stamp: tuple[int, int]) -> bytes:
    """A stamped message's CDR (its std_msgs/Header first) with the header's stamp replaced; RosNavError if it is
    not CDR. The relay stamps the service's outputs with the camera frame's exact stamp (a float loses it)."""
    if len(payload) < 12 or payload[:2] not in (b"\x00\x00", b"\x00\x01"):
        raise RosNavError(f"not a stamped message's CDR: {payload[:12]!r}")
    order = "<" if payload[1] == 1 else ">"
    return payload[:4] + struct.pack(order + "iI", *stamp) + payload[12:]


def yaw_of_quaternion(x: float, y: float, z: float, w: float) -> float:
    """The heading (rotation about z) of a unit quaternion: the one conversion, for odometry and tf."""
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def occupancy_grid_geometry(payload: bytes) -> GridGeometry:
    """The geometry of an OccupancyGrid's CDR; RosNavError when it is not one."""
    return read_occupancy_grid(payload)[0]


def read_occupancy_grid(payload: bytes) -> tuple[GridGeometry, NDArray[np.int8]]:
    """An OccupancyGrid's CDR: its geometry and its cells (rows i = y, a copy); RosNavError when it is not one."""
    try:
        reader = _Reader(payload)
        sec, nanosec, frame_id = reader.number("i"), reader.number("I"), reader.string()
        reader.number("i"), reader.number("I")  # map_load_time
        resolution = struct.unpack("<f", struct.pack("<I", reader.number("I")))[0]
        width, height = reader.number("I"), reader.number("I")
        x, y = _double(reader), _double(reader)
        for _ in range(5):  # origin's z and orientation: a mask's centre is all the relay needs
            _double(reader)
        cells = reader.octets()
    except _Malformed as err:
        raise RosNavError(f"not a {OCCUPANCY_GRID}: {err}") from None
    if len(cells) != width * height or not (resolution > 0 and math.isfinite(x) and math.isfinite(y)):
        raise RosNavError(f"a {OCCUPANCY_GRID} of {width}x{height} cells of {resolution} m with {len(cells)} values")
    geometry = GridGeometry(frame_id, float(resolution), width, height, (x, y), seconds((sec, nanosec)))
    return geometry, np.frombuffer(cells, np.int8).reshape(height, width).copy()


def odometry_pose(payload: bytes) -> Pose2D:
    """The pose of an Odometry's CDR (its stamp, frame, x, y, yaw), as a grid's pose stream and the relay read
    it: an empty frame id is ``odom``; RosNavError when it is not one or the pose is not usable."""
    try:
        reader = _Reader(payload)
        sec, nanosec, frame_id = reader.number("i"), reader.number("I"), reader.string()
        reader.string()  # child_frame_id
        x, y, _ = _double(reader), _double(reader), _double(reader)
        qx, qy, qz, qw = (_double(reader) for _ in range(4))
    except _Malformed as err:
        raise RosNavError(f"not a {ODOMETRY}: {err}") from None
    fields = {"x": x, "y": y, "yaw": yaw_of_quaternion(qx, qy, qz, qw)}
    try:
        return Pose2D.validated(
            {"stamp": seconds((sec, nanosec)), "frame_id": frame_id or DEFAULT_ODOMETRY_FRAME, **fields}
        )
    except MessageError as err:
        raise RosNavError(f"a {ODOMETRY} whose pose is not usable: {err}") from None


def _double(reader: _Reader) -> float:
    low = reader.number("Q")
    return float(struct.unpack("<d", struct.pack("<Q", low))[0])


def odometry_motion(payload: bytes) -> Odometry2D:
    """An Odometry's CDR as the velocity tracker reads it: its pose and its twist (in the child frame);
    RosNavError when it is not one or a number is not finite."""
    pose = odometry_pose(payload)
    try:
        reader = _Reader(payload)
        reader.number("i"), reader.number("I"), reader.string(), reader.string()  # header, child_frame_id
        for _ in range(7 + COVARIANCE):  # the pose read above, and its covariance
            _double(reader)
        vx, vy, _, _, _, wz = (_double(reader) for _ in range(6))
        return Odometry2D(
            stamp=pose.stamp, frame_id=pose.frame_id, x=pose.x, y=pose.y, yaw=pose.yaw, vx=vx, vy=vy, wz=wz
        )
    except (_Malformed, ValueError) as err:  # pydantic's ValidationError is a ValueError: a number not finite
        raise RosNavError(f"not a usable {ODOMETRY}: {err}") from None


def twist_command(payload: bytes, stamped: bool) -> Twist2D:
    """A Twist's or TwistStamped's CDR as a velocity command; RosNavError when it is not one."""
    try:
        reader = _Reader(payload)
        if stamped:
            reader.number("i"), reader.number("I"), reader.string()
        vx, vy, _, _, _, wz = (_double(reader) for _ in range(6))
        return Twist2D(vx=vx, vy=vy, wz=wz)
    except (_Malformed, ValueError) as err:
        raise RosNavError(f"not a usable {TWIST_STAMPED if stamped else TWIST}: {err}") from None


def bool_value(payload: bytes) -> bool:
    """A std_msgs/Bool's CDR; RosNavError when it is not one."""
    if len(payload) < 5 or payload[:2] not in (b"\x00\x00", b"\x00\x01") or payload[4] > 1:
        raise RosNavError(f"not a {BOOL}: {payload[:8]!r}")
    return bool(payload[4])


def path_points(payload: bytes) -> tuple[str, float, list[tuple[float, float]]]:
    """A Path's CDR as the outcomes read it: its header's frame id and stamp, and its poses' (x, y) in order (the
    poses' own headers are skipped: the path's frame is the grid's); RosNavError when it is not one."""
    try:
        reader = _Reader(payload)
        sec, nanosec, frame_id = reader.number("i"), reader.number("I"), reader.string()
        count = reader.number("I")
        if count * POSE_STAMPED_BYTES > len(payload):  # a corrupt count must not loop for long
            raise _Malformed(f"{count} poses in {len(payload)} bytes")
        points = []
        for _ in range(count):
            reader.number("i"), reader.number("I"), reader.string()
            x, y = _double(reader), _double(reader)
            for _ in range(5):  # z and the orientation
                _double(reader)
            points.append((x, y))
    except _Malformed as err:
        raise RosNavError(f"not a {PATH}: {err}") from None
    if not all(math.isfinite(x) and math.isfinite(y) for x, y in points):
        raise RosNavError(f"a {PATH} with a position that is not finite")
    return frame_id, seconds((sec, nanosec)), points
