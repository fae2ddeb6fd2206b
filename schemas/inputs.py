"""Turn an input payload into an RGB image with its stamp and frame id, or a clear rejection."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from gcdtrav.schemas.images import ImageDecodeError, decode_image
from gcdtrav.schemas.messages import RAW_CHANNELS, ImageEnvelope, MessageError, PixelEncoding
from numpy.typing import NDArray


class RejectedInput(ValueError):
    """An input the service will not process (image payload, ROS message or key, graph token); ``reason`` is
    its code for counting (``rejected_by_reason`` in the status), ``detail`` the human half."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


@dataclass(frozen=True)
class DecodedFrame:
    image: NDArray[np.uint8]  # (H, W, 3) RGB
    stamp: float
    frame_id: str


def _looks_like_msgpack_map(payload: bytes) -> bool:
    first = payload[0]
    return 0x80 <= first <= 0x8F or first in (0xDE, 0xDF)


def decode_payload(payload: bytes, encoding: str, received_at: float, max_bytes: int, max_pixels: int) -> DecodedFrame:
    """JPEG/PNG bytes (by zenoh encoding or content) or an ImageEnvelope (msgpack)."""
    if len(payload) > max_bytes:
        raise RejectedInput("oversized", f"{len(payload)} bytes exceeds the limit of {max_bytes}")
    if not payload:
        raise RejectedInput("empty", "payload has 0 bytes")
    if encoding.startswith("application/msgpack") or (
        not encoding.startswith("image/") and _looks_like_msgpack_map(payload)
    ):
        return _decode_envelope(payload, max_bytes, max_pixels)
    try:
        return DecodedFrame(decode_image(payload, max_pixels), stamp=received_at, frame_id="")
    except ImageDecodeError as err:
        raise RejectedInput(err.reason, str(err)) from None


def _decode_envelope(payload: bytes, max_bytes: int, max_pixels: int) -> DecodedFrame:
    try:
        envelope = ImageEnvelope.unpack(payload, max_bytes)
    except MessageError as err:
        raise RejectedInput("malformed_envelope", str(err)) from None
    if envelope.width * envelope.height > max_pixels:
        raise RejectedInput(
            "too_many_pixels", f"{envelope.width}x{envelope.height} exceeds the limit of {max_pixels} pixels"
        )
    if envelope.encoding in RAW_CHANNELS:
        image = _raw_pixels(envelope)
    else:
        try:
            image = decode_image(envelope.data, max_pixels)
        except ImageDecodeError as err:
            raise RejectedInput(err.reason, f"envelope {envelope.encoding.value}: {err}") from None
    return DecodedFrame(image, stamp=envelope.stamp, frame_id=envelope.frame_id)


def _raw_pixels(envelope: ImageEnvelope) -> NDArray[np.uint8]:
    channels = RAW_CHANNELS[envelope.encoding]
    expected = envelope.width * envelope.height * channels
    if len(envelope.data) != expected:
        raise RejectedInput(
            "size_mismatch",
            f"{envelope.encoding.value} {envelope.width}x{envelope.height} needs {expected} bytes, "
            f"got {len(envelope.data)}",
        )
    pixels = np.frombuffer(envelope.data, np.uint8).reshape(envelope.height, envelope.width, channels)
    if envelope.encoding is PixelEncoding.BGR8:
        return np.ascontiguousarray(pixels[:, :, ::-1])
    if envelope.encoding is PixelEncoding.MONO8:
        return np.asarray(cv2.cvtColor(pixels[:, :, 0], cv2.COLOR_GRAY2RGB), dtype=np.uint8)
    return pixels.copy()
