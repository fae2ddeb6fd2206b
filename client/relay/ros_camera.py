"""ROS 2 camera images in CDR without ROS or rosbags: what the relay on a robot needs, numpy and OpenCV only.

sensor_msgs/msg/Image and CompressedImage in plain CDR (XCDR1, as rmw_zenoh and zenoh-bridge-ros2dds carry
them): a 4-byte encapsulation header (byte 1: 1 little-endian, 0 big-endian), then the fields, each aligned
to its size from the end of that header. The service decodes with rosbags (service/ros/cdr.py); a test
checks both agree.
"""

from __future__ import annotations

import struct

import cv2
import numpy as np
from gcdtrav.schemas.images import ImageDecodeError, decode_image
from numpy.typing import NDArray

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
# OpenCV names a Bayer pattern by its second row's first two pixels, ROS by the first row's (as cv_bridge).
_BAYER = {
    "bayer_rggb8": cv2.COLOR_BayerBG2RGB,
    "bayer_bggr8": cv2.COLOR_BayerRG2RGB,
    "bayer_gbrg8": cv2.COLOR_BayerGR2RGB,
    "bayer_grbg8": cv2.COLOR_BayerGB2RGB,
}
_CHANNELS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "mono16": 2, **dict.fromkeys(_BAYER, 1)}


class RosImageError(ValueError):
    """A payload that is not a usable Image or CompressedImage."""


class _Reader:
    def __init__(self, payload: bytes) -> None:
        if len(payload) < 4 or payload[0] != 0 or payload[1] not in (0, 1):
            raise RosImageError("not CDR: the encapsulation header must be 00 00 or 00 01")
        self.data = memoryview(payload)
        self.endian = "<" if payload[1] == 1 else ">"
        self.offset = 4

    def _align(self, size: int) -> None:
        self.offset += -(self.offset - 4) % size

    def number(self, code: str) -> int:
        size = struct.calcsize(code)
        self._align(size)
        if self.offset + size > len(self.data):
            raise RosImageError("truncated CDR")
        (value,) = struct.unpack_from(self.endian + code, self.data, self.offset)
        self.offset += size
        return int(value)

    def octets(self) -> memoryview:
        length = self.number("I")
        if self.offset + length > len(self.data):
            raise RosImageError(f"truncated CDR: a sequence of {length} bytes at {self.offset} of {len(self.data)}")
        chunk = self.data[self.offset : self.offset + length]
        self.offset += length
        return chunk

    def string(self) -> str:
        return bytes(self.octets()).rstrip(b"\x00").decode("utf-8", errors="replace")


class _Writer:
    def __init__(self) -> None:
        self.parts = bytearray(b"\x00\x01\x00\x00")

    def _align(self, size: int) -> None:
        self.parts += b"\x00" * (-(len(self.parts) - 4) % size)

    def number(self, code: str, value: int) -> None:
        self._align(struct.calcsize(code))
        self.parts += struct.pack("<" + code, value)

    def octets(self, data: bytes) -> None:
        self.number("I", len(data))
        self.parts += data

    def string(self, text: str) -> None:
        self.octets(text.encode("utf-8") + b"\x00")


def _header(reader: _Reader) -> tuple[float, str]:
    sec, nanosec = reader.number("i"), reader.number("I")
    return sec + nanosec * 1e-9, reader.string()


def _write_header(writer: _Writer, stamp: float, frame_id: str) -> None:
    sec = int(stamp // 1)
    writer.number("i", sec)
    writer.number("I", min(round((stamp - sec) * 1e9), 999_999_999))
    writer.string(frame_id)


def peek_stamp(payload: bytes) -> float:
    """The header stamp of any stamped ROS message (the header comes first), without the rest."""
    return _header(_Reader(payload))[0]


def decode_ros_image(payload: bytes, msgtype: str, max_pixels: int) -> tuple[NDArray[np.uint8], float, str]:
    """An Image or CompressedImage as (RGB pixels, header stamp, frame id); RosImageError when unusable."""
    reader = _Reader(payload)
    stamp, frame_id = _header(reader)
    if msgtype == COMPRESSED_IMAGE:
        reader.string()  # format: the pixels tell
        try:
            return decode_image(bytes(reader.octets()), max_pixels), stamp, frame_id
        except ImageDecodeError as err:
            raise RosImageError(f"CompressedImage: {err}") from None
    if msgtype != IMAGE:
        raise RosImageError(f"{msgtype} is not an image type ({IMAGE}, {COMPRESSED_IMAGE})")
    height, width = reader.number("I"), reader.number("I")
    encoding = reader.string().lower()
    big_endian, step = reader.number("B"), reader.number("I")
    data = reader.octets()
    return _raw_to_rgb(data, encoding, width, height, step, bool(big_endian), max_pixels), stamp, frame_id


def _raw_to_rgb(
    data: memoryview, encoding: str, width: int, height: int, step: int, big_endian: bool, max_pixels: int
) -> NDArray[np.uint8]:
    if encoding not in _CHANNELS:
        raise RosImageError(f"encoding '{encoding}' (supported: {', '.join(_CHANNELS)})")
    if width * height == 0 or width * height > max_pixels:
        raise RosImageError(f"an image of {width}x{height} pixels (limit {max_pixels})")
    row = width * _CHANNELS[encoding]
    if step < row or len(data) < step * height:
        raise RosImageError(f"{encoding} {width}x{height}, step {step}: {len(data)} bytes are too few")
    rows = np.frombuffer(data, np.uint8, count=step * height).reshape(height, step)[:, :row]
    if encoding == "mono16":  # the top byte, as cv_bridge's mono16 -> mono8
        gray = rows.reshape(height, width, 2)[:, :, 0 if big_endian else 1]
        return np.repeat(gray[:, :, None], 3, axis=2)
    pixels = rows.reshape(height, width, _CHANNELS[encoding])
    if encoding in _BAYER:
        return np.asarray(cv2.cvtColor(np.ascontiguousarray(pixels[:, :, 0]), _BAYER[encoding]), np.uint8)
    if encoding == "mono8":
        return np.repeat(pixels, 3, axis=2)
    rgb = pixels[:, :, 2::-1] if encoding.startswith("bgr") else pixels[:, :, :3]
    return np.ascontiguousarray(rgb)


def image_cdr(pixels: NDArray[np.uint8], stamp: float, frame_id: str = "", encoding: str = "rgb8") -> bytes:
    """A sensor_msgs/msg/Image (little-endian) of packed rows: what a camera driver publishes."""
    height, width = pixels.shape[:2]
    data = np.ascontiguousarray(pixels).tobytes()
    writer = _Writer()
    _write_header(writer, stamp, frame_id)
    writer.number("I", height)
    writer.number("I", width)
    writer.string(encoding)
    writer.number("B", 0)
    writer.number("I", len(data) // height)
    writer.octets(data)
    return bytes(writer.parts)


def compressed_image_cdr(jpeg: bytes, stamp: float, frame_id: str = "", image_format: str = "jpeg") -> bytes:
    """A sensor_msgs/msg/CompressedImage (little-endian), as image_transport's compressed plugin sends."""
    writer = _Writer()
    _write_header(writer, stamp, frame_id)
    writer.string(image_format)
    writer.octets(jpeg)
    return bytes(writer.parts)


def ros_type_of_chunk(chunk: str) -> str | None:
    """sensor_msgs::msg::dds_::Image_ (an rmw_zenoh key chunk) -> sensor_msgs/msg/Image; None otherwise."""
    parts = chunk.split("::")
    if len(parts) == 4 and parts[2] == "dds_" and parts[3].endswith("_"):
        return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"
    return None


def ros_camera_key(topic: str, layout: str, domain: int = 0, namespace: str = "") -> str:
    """The key expression of a camera topic's messages: rmw_zenoh '<domain>/<topic>/<type>/<hash>' (any type
    and hash) or the bridge's topic name."""
    name = topic.strip("/")
    key = name if layout == "bridge" else f"{domain}/{name}/*/*"
    return f"{namespace}/{key}" if namespace else key


def ros_type_of_key(key: str) -> str | None:
    """The message type an rmw_zenoh key names (its second-to-last chunk)."""
    chunks = key.split("/")
    return ros_type_of_chunk(chunks[-2]) if len(chunks) >= 3 else None
