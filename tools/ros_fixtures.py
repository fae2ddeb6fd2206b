"""ROS 2 messages as a robot publishes them, and decoders of what the service publishes: for the tests,
benchmarks and examples, never the service (the wheel holds only what the service and the relay run).

- camera images as a driver sends them (``image_cdr``, ``compressed_image_cdr``), written by hand with numpy
  like the one reader (schemas/ros_image.py), so they need no ROS typestore;
- a robot's velocity commands, odometry and tf (``twist_cdr``, ``odometry_cdr``, ``tf_message_cdr``);
- the grid's GridMap read back (``decode_grid_map``).
"""

from __future__ import annotations

import math
import struct
from typing import Any

import numpy as np
from gcdtrav.service.ros.cdr import make_header, typestore
from gcdtrav.service.ros.grid_map import COLUMN_INDEX, ROW_INDEX
from gcdtrav.service.ros.grid_map_msgs import GRID_MAP
from gcdtrav.service.ros.tf import TF_MESSAGE, StampedTransform
from numpy.typing import NDArray

# ---- camera images ------------------------------------------------------------------------------------------


class _Writer:
    def __init__(self) -> None:
        self.parts = bytearray(b"\x00\x01\x00\x00")

    def number(self, code: str, value: int) -> None:
        self.parts += b"\x00" * (-(len(self.parts) - 4) % struct.calcsize(code))
        self.parts += struct.pack("<" + code, value)

    def octets(self, data: bytes) -> None:
        self.number("I", len(data))
        self.parts += data

    def string(self, text: str) -> None:
        self.octets(text.encode("utf-8") + b"\x00")

    def header(self, stamp: float, frame_id: str) -> None:
        sec = int(stamp // 1)
        self.number("i", sec)
        self.number("I", min(round((stamp - sec) * 1e9), 999_999_999))
        self.string(frame_id)


def image_cdr(pixels: NDArray[np.uint8], stamp: float, frame_id: str = "", encoding: str = "rgb8") -> bytes:
    """A sensor_msgs/msg/Image (little-endian) of packed rows."""
    height = pixels.shape[0]
    data = np.ascontiguousarray(pixels).tobytes()
    writer = _Writer()
    writer.header(stamp, frame_id)
    writer.number("I", height)
    writer.number("I", pixels.shape[1])
    writer.string(encoding)
    writer.number("B", 0)
    writer.number("I", len(data) // height)
    writer.octets(data)
    return bytes(writer.parts)


def compressed_image_cdr(jpeg: bytes, stamp: float, frame_id: str = "", image_format: str = "jpeg") -> bytes:
    """A sensor_msgs/msg/CompressedImage (little-endian), as image_transport's compressed plugin sends."""
    writer = _Writer()
    writer.header(stamp, frame_id)
    writer.string(image_format)
    writer.octets(jpeg)
    return bytes(writer.parts)


# ---- a robot's motion and tf ----------------------------------------------------------------------------


def twist_cdr(vx: float, vy: float = 0.0, wz: float = 0.0) -> bytes:
    types = typestore().types
    vector = types["geometry_msgs/msg/Vector3"]
    message = types["geometry_msgs/msg/Twist"](linear=vector(x=vx, y=vy, z=0.0), angular=vector(x=0.0, y=0.0, z=wz))
    return bytes(typestore().serialize_cdr(message, "geometry_msgs/msg/Twist"))


def odometry_cdr(stamp: float, x: float, y: float, yaw: float, vx: float, vy: float = 0.0, wz: float = 0.0) -> bytes:
    """nav_msgs/msg/Odometry in frame 'odom', child 'base_link' (tests, benchmarks and simulated robots)."""
    types = typestore().types
    vector, point = types["geometry_msgs/msg/Vector3"], types["geometry_msgs/msg/Point"]
    quaternion = types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))
    pose = types["geometry_msgs/msg/PoseWithCovariance"](
        pose=types["geometry_msgs/msg/Pose"](position=point(x=x, y=y, z=0.0), orientation=quaternion),
        covariance=np.zeros(36),
    )
    twist = types["geometry_msgs/msg/TwistWithCovariance"](
        twist=types["geometry_msgs/msg/Twist"](linear=vector(x=vx, y=vy, z=0.0), angular=vector(x=0.0, y=0.0, z=wz)),
        covariance=np.zeros(36),
    )
    message = types["nav_msgs/msg/Odometry"](
        header=make_header(stamp, "odom"), child_frame_id="base_link", pose=pose, twist=twist
    )
    return bytes(typestore().serialize_cdr(message, "nav_msgs/msg/Odometry"))


def tf_message_cdr(transforms: list[StampedTransform]) -> bytes:
    """A TFMessage's CDR bytes (tests, examples and simulated robots publish these)."""
    types = typestore().types
    vector, quaternion = types["geometry_msgs/msg/Vector3"], types["geometry_msgs/msg/Quaternion"]
    items = []
    for item in transforms:
        t, q = item.transform.translation, item.transform.rotation
        items.append(
            types["geometry_msgs/msg/TransformStamped"](
                header=make_header(item.stamp, item.parent),
                child_frame_id=item.child,
                transform=types["geometry_msgs/msg/Transform"](
                    translation=vector(x=t[0], y=t[1], z=t[2]), rotation=quaternion(x=q[0], y=q[1], z=q[2], w=q[3])
                ),
            )
        )
    return bytes(typestore().serialize_cdr(types[TF_MESSAGE](transforms=items), TF_MESSAGE))


# ---- the grid read back ----------------------------------------------------------------------------------------


def from_grid_map_order(data: NDArray[Any], cells_x: int, cells_y: int) -> NDArray[np.float32]:
    """The inverse of ``to_grid_map_order``: grid_map's data array back to a gcdtrav layer."""
    return np.asarray(data, np.float32).reshape(cells_y, cells_x)[::-1, ::-1].copy()


def decode_grid_map(payload: bytes) -> tuple[Any, dict[str, NDArray[np.float32]]]:
    """A GridMap CDR's message and its layers as gcdtrav layers (row i = y, column j = x); start indices must
    be 0 and the storage column-major, as grid_map_cdr writes them."""
    message = typestore().deserialize_cdr(payload, GRID_MAP)
    if message.outer_start_index or message.inner_start_index:
        raise ValueError("a GridMap with a circular-buffer start index is not supported here")
    layers = {}
    for name, array in zip(message.layers, message.data, strict=True):
        column, row = array.layout.dim
        if (column.label, row.label) != (COLUMN_INDEX, ROW_INDEX):
            raise ValueError(f"layer {name}: dims {column.label}, {row.label}: not column-major")
        layers[str(name)] = from_grid_map_order(array.data, int(row.size), int(column.size))
    return message, layers
