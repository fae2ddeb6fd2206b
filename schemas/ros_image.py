"""ROS 2 camera images in CDR, read with numpy and OpenCV only: the one reader of sensor_msgs/msg/Image and
CompressedImage, for the service (service/ros/cdr.py adds the header its ROS outputs reuse) and for the relay
on a robot (client/relay/), neither of which needs ROS.

Plain CDR (XCDR1, as rmw_zenoh and zenoh-bridge-ros2dds carry it): a 4-byte encapsulation header (byte 1: 1
little-endian, 0 big-endian), then the fields, each aligned to its size from the end of that header. The
rules are those of rosbags' deserialiser, which the service used before: a string holds at least its NUL
terminator and is UTF-8; a sequence fits in the payload; at most 3 bytes of padding may follow the message.
Whatever is unusable raises ``RejectedInput`` with the reason the service counts.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import cv2
import numpy as np
from gcdtrav.schemas.images import ImageDecodeError, decode_image
from gcdtrav.schemas.inputs import RejectedInput
from gcdtrav.schemas.limits import MAX_FRAME_ID_CHARS
from numpy.typing import NDArray

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
SUPPORTED_TYPES = (IMAGE, COMPRESSED_IMAGE)
# OpenCV names a Bayer pattern by its second row's first two pixels, ROS by the first row's (as cv_bridge).
BAYER = {
    "bayer_rggb8": cv2.COLOR_BayerBG2RGB,
    "bayer_bggr8": cv2.COLOR_BayerRG2RGB,
    "bayer_gbrg8": cv2.COLOR_BayerGR2RGB,
    "bayer_grbg8": cv2.COLOR_BayerGB2RGB,
}
# bytes per pixel of each raw encoding we accept; Bayer patterns are one 8-bit channel
RAW_ENCODINGS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "mono16": 2, **dict.fromkeys(BAYER, 1)}
MAX_PADDING = 3  # bytes after the message: CDR pads to 4 (rosbags refuses more)


def ros_type_name(dds_name: str) -> str | None:
    """sensor_msgs::msg::dds_::Image_ (an rmw_zenoh key chunk) -> sensor_msgs/msg/Image; None otherwise."""
    parts = dds_name.split("::")
    if len(parts) == 4 and parts[2] == "dds_" and parts[3].endswith("_"):
        return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"
    return None


class _Malformed(ValueError):
    """Not the message's CDR: reported as ``bad_cdr``."""


@dataclass(frozen=True)
class RosImage:
    image: NDArray[np.uint8]  # (H, W, 3) RGB
    sec: int  # the header's stamp, exactly
    nanosec: int
    frame_id: str

    @property
    def stamp(self) -> float:
        return self.sec + self.nanosec * 1e-9


class _Reader:
    def __init__(self, payload: bytes) -> None:
        if len(payload) < 4 or payload[:2] not in (b"\x00\x00", b"\x00\x01"):
            raise _Malformed("Invalid or unsupported CDR encapsulation.")
        self.data = memoryview(payload)
        self.endian = "<" if payload[1] == 1 else ">"
        self.offset = 4

    def number(self, code: str) -> int:
        size = struct.calcsize(code)
        self.offset += -(self.offset - 4) % size
        if self.offset + size > len(self.data):
            raise _Malformed(f"truncated at {self.offset} of {len(self.data)} bytes")
        (value,) = struct.unpack_from(self.endian + code, self.data, self.offset)
        self.offset += size
        return int(value)

    def octets(self) -> memoryview:
        length = self.number("I")
        if self.offset + length > len(self.data):
            raise _Malformed(f"a sequence of {length} bytes at {self.offset} of {len(self.data)}")
        chunk = self.data[self.offset : self.offset + length]
        self.offset += length
        return chunk

    def string(self) -> str:
        at = self.offset
        raw = self.octets()
        if len(raw) < 1 or raw[-1] != 0:
            raise _Malformed(f"a string without its terminator at {at}")
        try:
            return bytes(raw[:-1]).decode("utf-8")
        except UnicodeDecodeError as err:
            raise _Malformed(f"a string that is not UTF-8 at {at}: {err}") from None

    def end(self) -> None:
        if len(self.data) - self.offset > MAX_PADDING:
            raise _Malformed(f"{len(self.data) - self.offset} bytes after the message")


def peek_stamp(payload: bytes) -> float | None:
    """The header stamp of any stamped ROS message (the header comes first), without the rest; None when the
    payload is too short or not CDR."""
    try:
        reader = _Reader(payload)
        return reader.number("i") + reader.number("I") * 1e-9
    except _Malformed:
        return None


def decode_ros_image(payload: bytes, msgtype: str, max_pixels: int) -> RosImage:
    """An Image or CompressedImage as RGB pixels, sizes checked before any pixel is touched; RejectedInput
    (unsupported_ros_type, bad_cdr, frame_id_too_long, unknown_encoding, size_mismatch, too_many_pixels,
    undecodable) when unusable."""
    if msgtype not in SUPPORTED_TYPES:
        raise RejectedInput("unsupported_ros_type", f"{msgtype} (supported: {', '.join(SUPPORTED_TYPES)})")
    try:
        reader = _Reader(payload)
        sec, nanosec, frame_id = reader.number("i"), reader.number("I"), reader.string()
        compressed = _compressed_fields(reader) if msgtype == COMPRESSED_IMAGE else None
        raw = _raw_fields(reader) if compressed is None else None
        reader.end()
    except _Malformed as err:
        raise RejectedInput("bad_cdr", f"{msgtype} does not deserialise: {err}") from None
    if len(frame_id) > MAX_FRAME_ID_CHARS:
        raise RejectedInput(
            "frame_id_too_long", f"frame_id of {len(frame_id)} characters is over the limit of {MAX_FRAME_ID_CHARS}"
        )
    if raw is not None:
        return RosImage(_raw_to_rgb(*raw, max_pixels), sec, nanosec, frame_id)
    assert compressed is not None
    image_format, data = compressed
    try:
        return RosImage(decode_image(bytes(data), max_pixels), sec, nanosec, frame_id)
    except ImageDecodeError as err:
        raise RejectedInput("undecodable", f"CompressedImage ({image_format}): {err}") from None


def _compressed_fields(reader: _Reader) -> tuple[str, memoryview]:
    return reader.string(), reader.octets()


def _raw_fields(reader: _Reader) -> tuple[int, int, str, int, int, memoryview]:
    height, width, encoding = reader.number("I"), reader.number("I"), reader.string()
    big_endian, step = reader.number("B"), reader.number("I")
    return height, width, encoding, big_endian, step, reader.octets()


def _raw_to_rgb(
    height: int, width: int, encoding: str, big_endian: int, step: int, data: memoryview, max_pixels: int
) -> NDArray[np.uint8]:
    name = encoding.lower()
    if name not in RAW_ENCODINGS:
        raise RejectedInput("unknown_encoding", f"'{encoding}' (supported: {', '.join(RAW_ENCODINGS)})")
    if width <= 0 or height <= 0:
        raise RejectedInput("size_mismatch", f"image of {width}x{height} pixels")
    if width * height > max_pixels:
        raise RejectedInput("too_many_pixels", f"{width}x{height} exceeds the limit of {max_pixels} pixels")
    channels = RAW_ENCODINGS[name]
    row = width * channels
    if step < row or len(data) != step * height:
        raise RejectedInput(
            "size_mismatch",
            f"{name} {width}x{height}, step {step}: needs step >= {row} and "
            f"{step}x{height} = {step * height} bytes, got {len(data)}",
        )
    rows = np.frombuffer(data, np.uint8).reshape(height, step)[:, :row]  # row padding dropped
    if name == "mono16":  # the top byte, as cv_bridge's mono16 -> mono8
        gray = rows.reshape(height, width, 2)[:, :, 0 if big_endian else 1]
        return np.ascontiguousarray(np.repeat(gray[:, :, None], 3, axis=2))
    pixels = rows.reshape(height, width, channels)
    if name in BAYER:
        return np.asarray(cv2.cvtColor(np.ascontiguousarray(pixels[:, :, 0]), BAYER[name]), np.uint8)
    if name == "mono8":
        return np.ascontiguousarray(np.repeat(pixels, 3, axis=2))
    rgb = pixels[:, :, 2::-1] if name.startswith("bgr") else pixels[:, :, :3]
    return np.ascontiguousarray(rgb)
