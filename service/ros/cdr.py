"""ROS 2 messages over Zenoh, without a ROS installation: CDR via rosbags (camera images read by
schemas/ros_image.py, numpy only).

Two key layouts reach Zenoh:
  rmw_zenoh                 [<zenoh namespace>/]<domain>/<topic>/<type>/<type hash>, e.g.
                            0/camera/front/image_raw/sensor_msgs::msg::dds_::Image_/RIHS01_d31d...
                            (Humble robots write TypeHashNotSupported for the hash)
  zenoh-bridge-ros2dds      the topic name: camera/front/image_raw
The payload is the CDR-serialised message (with its 4-byte encapsulation header) in both.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
from gcdtrav.schemas import ros_image
from gcdtrav.schemas.inputs import RejectedInput
from gcdtrav.schemas.limits import MAX_FRAME_ID_CHARS
from gcdtrav.schemas.messages import GridHeader, MessageError, Pose2D
from gcdtrav.schemas.ros_image import COMPRESSED_IMAGE as COMPRESSED_IMAGE  # re-exported: the ROS types in one place
from gcdtrav.schemas.ros_image import IMAGE as IMAGE
from gcdtrav.schemas.ros_image import ros_type_name as ros_type_name  # re-exported: the bus's graph reads it
from gcdtrav.schemas.ros_nav import costmap_filter_info_cdr as costmap_filter_info_cdr  # re-exported, as below
from gcdtrav.schemas.ros_nav import occupancy_grid_cdr, odometry_pose, split_stamp
from gcdtrav.schemas.ros_nav import yaw_of_quaternion as yaw_of_quaternion  # re-exported: tf's too
from gcdtrav.schemas.settings.ros import output_topic as output_topic  # re-exported: the service's callers use it
from gcdtrav.service.grid.geometry import PinholeCamera
from gcdtrav.service.ros.grid_map_msgs import GRID_MAP as GRID_MAP  # re-exported: the output types in one place
from gcdtrav.service.ros.grid_map_msgs import register_types
from gcdtrav.service.ros.nav2_msgs import COSTMAP as NAV2_COSTMAP  # re-exported: the output types in one place
from gcdtrav.service.ros.nav2_msgs import COSTMAP_FILTER_INFO as COSTMAP_FILTER_INFO  # re-exported
from gcdtrav.service.ros.nav2_msgs import SPEED_LIMIT as SPEED_LIMIT
from gcdtrav.service.ros.nav2_msgs import register_types as register_nav2_types
from numpy.typing import NDArray

OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
HUMBLE_HASH = "TypeHashNotSupported"  # rmw_zenoh on Humble: the type-hash chunk of every key and token
# image_transport's "compressed" format string: the original encoding; the codec and what it holds
PREVIEW_FORMAT = "rgb8; jpeg compressed bgr8"


@cache
def typestore() -> Any:
    """Message definitions of ROS 2 Jazzy (rmw_zenoh's first release): sensor_msgs are the same since Humble.
    grid_map_msgs and nav2_msgs' speed filter messages, not built in, registered from their .msg text
    (service/ros/grid_map_msgs.py, service/ros/nav2_msgs.py)."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    register_types(store)
    register_nav2_types(store)
    return store


def dds_type_name(msgtype: str) -> str:
    """sensor_msgs/msg/Image -> sensor_msgs::msg::dds_::Image_ (rmw_zenoh's key chunk)."""
    package, kind, name = msgtype.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def type_hash(msgtype: str) -> str:
    return str(typestore().hash_rihs01(msgtype))


def output_type_hash(msgtype: str, input_hash: str | None) -> str:
    """The hash chunk a derived topic carries: Humble's placeholder for Humble inputs, else the Jazzy hash."""
    return HUMBLE_HASH if input_hash == HUMBLE_HASH else type_hash(msgtype)


@dataclass(frozen=True)
class RosTopic:
    """Where a ROS message came from: its topic, message type and the key layout it used."""

    topic: str  # with a leading slash: /camera/front/image_raw
    msgtype: str | None
    layout: str  # "rmw_zenoh" or "bridge"
    domain: int = 0
    namespace: str = ""  # the robot's zenoh namespace, prefixed to all its keys
    type_hash: str | None = None  # the key's hash chunk (rmw_zenoh); None: the Jazzy hash of msgtype

    @property
    def source(self) -> str:
        name = self.topic.lstrip("/")
        return f"{self.namespace}/{name}" if self.namespace else name

    def derived(self, topic: str, msgtype: str) -> RosTopic:
        """Another topic of the same robot, in the same layout, domain, namespace and ROS distribution."""
        return RosTopic(
            topic, msgtype, self.layout, self.domain, self.namespace, output_type_hash(msgtype, self.type_hash)
        )


def strip_namespace(key: str, namespace: str) -> str:
    if not namespace:
        return key
    if not key.startswith(namespace + "/"):
        raise RejectedInput("bad_ros_key", f"'{key}' does not start with the zenoh namespace '{namespace}/'")
    return key[len(namespace) + 1 :]


def parse_key(key: str, layout: str, namespace: str = "") -> RosTopic:
    """Topic and (for rmw_zenoh) message type and hash from a key, after the robot's zenoh namespace."""
    local = strip_namespace(key, namespace)
    if layout == "bridge":
        return RosTopic("/" + local, None, "bridge", namespace=namespace)
    chunks = local.split("/")
    for index, chunk in enumerate(chunks):
        msgtype = ros_type_name(chunk)
        if msgtype is not None and index >= 2:
            domain = int(chunks[0]) if chunks[0].isdigit() else 0
            hash_chunk = chunks[index + 1] if index + 1 < len(chunks) else None
            return RosTopic("/" + "/".join(chunks[1:index]), msgtype, "rmw_zenoh", domain, namespace, hash_chunk)
    raise RejectedInput("bad_ros_key", f"'{key}' is not <domain>/<topic>/<pkg::msg::dds_::Type_>/<hash>")


def topic_key(topic: RosTopic) -> str:
    """The zenoh key a ROS publisher of ``topic`` uses in its layout, with the robot's zenoh namespace."""
    name = topic.topic.strip("/")
    if topic.layout == "bridge":
        key = name
    elif topic.msgtype is None:
        raise ValueError(f"an rmw_zenoh key needs the message type of {topic.topic}")
    else:
        key = f"{topic.domain}/{name}/{dds_type_name(topic.msgtype)}/{topic.type_hash or type_hash(topic.msgtype)}"
    return f"{topic.namespace}/{key}" if topic.namespace else key


def is_output_topic(topic: str, templates: list[str]) -> bool:
    """Whether ``topic`` is one a service with these templates publishes (never taken as an input)."""
    for template in templates:
        head, _, tail = template.strip("/").partition("{topic}")
        pattern = re.escape(head) + (".+" if "{topic}" in template else "") + re.escape(tail)
        if re.fullmatch(pattern, topic.strip("/")):
            return True
    return False


@dataclass(frozen=True)
class RosFrame:
    image: NDArray[np.uint8]  # (H, W, 3) RGB
    stamp: float
    frame_id: str
    header: Any  # std_msgs/Header, reused on the outputs


def decode_ros_image(payload: bytes, msgtype: str, max_pixels: int) -> RosFrame:
    """CDR Image/CompressedImage -> RGB (read by schemas/ros_image.py, the one reader), with the message's
    header for the ROS outputs; RejectedInput when unusable."""
    frame = ros_image.decode_ros_image(payload, msgtype, max_pixels)
    return RosFrame(frame.image, frame.stamp, frame.frame_id, header_of(frame.sec, frame.nanosec, frame.frame_id))


# ---- outputs ---------------------------------------------------------------------------------------


def _image_message(header: Any, array: NDArray[Any], encoding: str) -> Any:
    image_type = typestore().types[IMAGE]
    height, width = array.shape[:2]
    data = np.ascontiguousarray(array).view(np.uint8).ravel()
    return image_type(
        header=header,
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=len(data) // height,
        data=data,
    )


def float_image_cdr(header: Any, values: NDArray[np.floating]) -> bytes:
    """A 32FC1 sensor_msgs/Image (little-endian), e.g. T or U."""
    message = _image_message(header, np.asarray(values, dtype="<f4"), "32FC1")
    return bytes(typestore().serialize_cdr(message, IMAGE))


def rgb_image_cdr(header: Any, rgb: NDArray[np.uint8]) -> bytes:
    return bytes(typestore().serialize_cdr(_image_message(header, rgb, "rgb8"), IMAGE))


def compressed_jpeg_cdr(header: Any, jpeg: bytes) -> bytes:
    message = typestore().types[COMPRESSED_IMAGE](
        header=header, format=PREVIEW_FORMAT, data=np.frombuffer(jpeg, dtype=np.uint8)
    )
    return bytes(typestore().serialize_cdr(message, COMPRESSED_IMAGE))


def make_header(stamp: float, frame_id: str) -> Any:
    sec, nanosec = split_stamp(stamp)
    return header_of(sec, nanosec, frame_id)


def header_of(sec: int, nanosec: int, frame_id: str) -> Any:
    """A std_msgs/Header of exactly this stamp (a float would round its nanoseconds)."""
    types = typestore().types
    return types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id
    )


# ---- the ground grid's inputs and output -------------------------------------------------------------------


def decode_pose(payload: bytes, fmt: str) -> Pose2D:
    """A grid's pose stream: a Pose2D (``gcdtrav``) or an Odometry's CDR (the relay's rule, schemas/ros_nav.py)."""
    return Pose2D.unpack(payload) if fmt == "gcdtrav" else odometry_pose(payload)


def decode_camera_info_frame(payload: bytes) -> tuple[PinholeCamera, str]:
    """sensor_msgs/CameraInfo CDR -> the intrinsics and its header's frame_id (the camera's optical frame)."""
    try:
        info = typestore().deserialize_cdr(payload, "sensor_msgs/msg/CameraInfo")
    except Exception as err:  # rosbags raises assorted errors on bad CDR
        raise MessageError(f"not a sensor_msgs/msg/CameraInfo: {type(err).__name__}: {err}") from None
    k = np.asarray(info.k, dtype=np.float64)
    if not (np.isfinite(k).all() and k[0] > 0 and k[4] > 0 and info.width > 0 and info.height > 0):
        raise MessageError(f"CameraInfo needs finite intrinsics, positive focal lengths and a size; k={k.tolist()}")
    camera = PinholeCamera(fx=k[0], fy=k[4], cx=k[2], cy=k[5], width=int(info.width), height=int(info.height))
    frame_id = str(info.header.frame_id)
    return camera, frame_id if len(frame_id) <= MAX_FRAME_ID_CHARS else ""


def decode_depth(payload: bytes) -> NDArray[np.float32]:
    """sensor_msgs/Image 32FC1 (metres) or 16UC1 (millimetres) to metres."""
    try:
        image = typestore().deserialize_cdr(payload, IMAGE)
    except Exception as err:  # rosbags raises assorted errors on bad CDR
        raise MessageError(f"not a sensor_msgs/msg/Image: {type(err).__name__}: {err}") from None
    kinds = {"32fc1": ("f4", 1.0), "16uc1": ("u2", 1e-3), "mono16": ("u2", 1e-3)}
    kind = kinds.get(str(image.encoding).lower())
    if (
        kind is None
        or image.step * image.height != len(image.data)
        or image.step < image.width * (4 if kind[0] == "f4" else 2)
    ):
        raise MessageError(f"depth must be 32FC1 or 16UC1 with matching size, got {image.encoding}")
    dtype = np.dtype((">" if image.is_bigendian else "<") + kind[0])
    rows = np.asarray(image.data, np.uint8).reshape(image.height, image.step)
    values = rows[:, : image.width * dtype.itemsize].copy().view(dtype)
    return (values.astype(np.float32) * np.float32(kind[1])).reshape(image.height, image.width)


def occupancy_cdr(header: GridHeader, values: NDArray[np.floating], known: NDArray[np.bool_]) -> bytes:
    """nav_msgs/OccupancyGrid with cells 0..100 where known, -1 elsewhere."""
    data = np.where(known, np.clip(np.round(np.nan_to_num(values) * 100), 0, 100), -1).astype(np.int8)
    return occupancy_values_cdr(header, data)


def occupancy_values_cdr(header: GridHeader, data: NDArray[np.int8]) -> bytes:
    """nav_msgs/OccupancyGrid of the grid's cells, given their values (row i = y, column j = x, as the grid):
    written as the relay writes its safe mask (schemas/ros_nav.py)."""
    cells = np.asarray(data, np.int8).reshape(header.cells, header.cells)
    return occupancy_grid_cdr(split_stamp(header.stamp), header.frame_id, header.resolution, header.origin, cells)


# Nav2's static layer reads an OccupancyGrid value v (nav2_costmap_2d/plugins/static_layer.cpp interpretValue,
# trinary_costmap false): -1 as NO_INFORMATION 255, 100 (lethal_cost_threshold) as LETHAL 254, else v / 100 x 254
NO_INFORMATION, LETHAL_OBSTACLE = 255, 254


def nav2_cost_values(data: NDArray[np.int8]) -> NDArray[np.uint8]:
    """The Nav2 costs of the costmap's OccupancyGrid values, as Nav2's static layer reads them."""
    graded = (data.astype(np.int32) * 254 // 100).astype(np.uint8)
    return np.where(data < 0, NO_INFORMATION, np.where(data >= 100, LETHAL_OBSTACLE, graded)).astype(np.uint8)


def nav2_costmap_cdr(header: GridHeader, data: NDArray[np.int8]) -> bytes:
    """nav2_msgs/Costmap of the grid's costmap values (its OccupancyGrid's, -1 .. 100), as Nav2 costs: what the
    collision monitor's costmap source reads. Stamped as the costmap, with the capture stamp of the newest fused
    frame: a source older than its ``source_timeout`` stops the robot (docs/ros2.md, "When the link dies")."""
    types = typestore().types
    ros_header = make_header(header.stamp, header.frame_id)
    pose = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=header.origin[0], y=header.origin[1], z=0.0),
        orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
    )
    metadata = types["nav2_msgs/msg/CostmapMetaData"](
        map_load_time=ros_header.stamp,
        update_time=ros_header.stamp,
        layer="gcdtrav",
        resolution=np.float32(header.resolution),
        size_x=header.cells,
        size_y=header.cells,
        origin=pose,
    )
    message = types[NAV2_COSTMAP](header=ros_header, metadata=metadata, data=nav2_cost_values(data).ravel())
    return bytes(typestore().serialize_cdr(message, NAV2_COSTMAP))


# ---- Nav2's speed filter: its info and the speed limit (docs/grid.md, "Speed from uncertainty") ------------


def speed_limit_cdr(stamp: float, frame_id: str, percent: float) -> bytes:
    """nav2_msgs/SpeedLimit in percent of the maximum speed; 0: no limit."""
    message = typestore().types[SPEED_LIMIT](header=make_header(stamp, frame_id), percentage=True, speed_limit=percent)
    return bytes(typestore().serialize_cdr(message, SPEED_LIMIT))
