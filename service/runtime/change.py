"""Has a source's view changed? A cheap measure on grey block means, and the pose's motion. No zenoh here.

The thumbnail: the frame in grey, averaged into ``blocks`` (columns x rows) block means, then its mean
subtracted and divided by its standard deviation. Exposure and gain flicker scale and shift every pixel
alike and cancel; sensor noise averages out over a block's hundreds of pixels. Two thumbnails differ by
the fraction of blocks whose normalised means differ by more than ``block_threshold``: a robust count (one
glint moves one block, a person walking in several), not a mean that noise over the whole view adds up to.

A JPEG is decoded at an eighth of its size, straight to grey (``cv2.IMREAD_REDUCED_GRAYSCALE_8``: the
decoder skips most of its work); other inputs are decoded as the worker would, then shrunk.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from gcdtrav.schemas.images import peek_image_size
from gcdtrav.schemas.inputs import decode_payload
from gcdtrav.schemas.messages import ImageEnvelope, MessageError, PixelEncoding, Pose2D, peek_fields
from gcdtrav.schemas.ros_image import decode_ros_image
from gcdtrav.schemas.settings.share import ReuseSettings
from gcdtrav.service.runtime.frames import PendingFrame
from numpy.typing import NDArray

MIN_CONTRAST = 8.0  # grey levels: a flatter view (a lens cap, darkness) is not stretched, its noise not amplified
JPEG_MAGIC = b"\xff\xd8"

Thumbnail = NDArray[np.float32]  # (rows, columns) normalised block means


@dataclass(frozen=True)
class Glance:
    """A frame looked at without inference: its thumbnail, stamp and frame id (as the decode would give)."""

    thumbnail: Thumbnail
    stamp: float
    frame_id: str
    size: tuple[int, int] | None = None  # (width, height) of the image; None: not known without decoding


def thumbnail_of_grey(grey: NDArray[np.uint8], blocks: tuple[int, int]) -> Thumbnail:
    """Block means of a grey image, mean-and-contrast normalised."""
    means = np.asarray(cv2.resize(grey, blocks, interpolation=cv2.INTER_AREA), np.float32)
    centred = means - means.mean()
    return np.asarray(centred / max(float(centred.std()), MIN_CONTRAST), np.float32)


def thumbnail_of_rgb(image: NDArray[np.uint8], blocks: tuple[int, int]) -> Thumbnail:
    return thumbnail_of_grey(np.asarray(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY), np.uint8), blocks)


def glance(pending: PendingFrame, max_bytes: int, max_pixels: int, blocks: tuple[int, int]) -> Glance:
    """The frame's thumbnail; raises what decoding it raises (the worker then counts the frame's fault)."""
    if pending.ros is not None:
        if pending.ros.msgtype is None:
            raise ValueError(f"no message type for '{pending.key}'")
        frame = decode_ros_image(pending.payload, pending.ros.msgtype, max_pixels)  # no header: nothing goes out
        return Glance(thumbnail_of_rgb(frame.image, blocks), frame.stamp, frame.frame_id, size_of(frame.image))
    jpeg, stamp, frame_id = _jpeg_inside(pending)
    if jpeg is not None:
        grey = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_REDUCED_GRAYSCALE_8)
        if grey is not None:
            return Glance(thumbnail_of_grey(np.asarray(grey, np.uint8), blocks), stamp, frame_id, peek_image_size(jpeg))
    decoded = decode_payload(pending.payload, pending.encoding, pending.received_at, max_bytes, max_pixels)
    return Glance(thumbnail_of_rgb(decoded.image, blocks), decoded.stamp, decoded.frame_id, size_of(decoded.image))


def size_of(image: NDArray[np.uint8]) -> tuple[int, int]:
    """(width, height)."""
    return int(image.shape[1]), int(image.shape[0])


def _jpeg_inside(pending: PendingFrame) -> tuple[bytes | None, float, str]:
    """A bare JPEG, or an envelope's JPEG data, with the stamp and frame id the decode would give."""
    payload = pending.payload
    if payload[:2] == JPEG_MAGIC:
        return payload, pending.received_at, ""
    try:
        if peek_fields(payload, ("encoding",)).get("encoding") != PixelEncoding.JPEG.value:
            return None, pending.received_at, ""
        envelope = ImageEnvelope.unpack(payload)
    except MessageError:
        return None, pending.received_at, ""
    return envelope.data, envelope.stamp, envelope.frame_id


def moved_fraction(a: Thumbnail, b: Thumbnail, block_threshold: float) -> float:
    """The fraction of blocks whose normalised means differ by more than ``block_threshold``."""
    if a.shape != b.shape:
        return 1.0
    return float(np.mean(np.abs(a - b) > block_threshold))


def pose_moved(a: Pose2D, b: Pose2D, settings: ReuseSettings) -> bool:
    """Moved or turned beyond the thresholds between two poses (turning in place counts)."""
    turned = abs(math.remainder(b.yaw - a.yaw, math.tau))
    return math.hypot(b.x - a.x, b.y - a.y) > settings.translation_m or turned > math.radians(settings.rotation_deg)


def pose_speeds(a: Pose2D, b: Pose2D) -> tuple[float, float] | None:
    """(m/s, degrees/s) from ``a`` to ``b`` by their stamps; None when they are not ordered in time."""
    dt = b.stamp - a.stamp
    if dt <= 0:
        return None
    turned = abs(math.remainder(b.yaw - a.yaw, math.tau))
    return math.hypot(b.x - a.x, b.y - a.y) / dt, math.degrees(turned) / dt
