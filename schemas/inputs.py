"""Turn an input payload into an RGB image with its stamp and frame id, or a clear rejection."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from gcdtrav.schemas.images import ImageDecodeError, decode_image
from gcdtrav.schemas.messages import MSGPACK_ENCODING, RAW_CHANNELS, ImageEnvelope, MessageError, PixelEncoding
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
    original_size: tuple[int, int] | None = None  # (width, height) of the camera's image, if the sender shrank it

    @property
    def camera_size(self) -> tuple[int, int]:
        """(width, height) in the camera's pixels: what the maps' geometry and the queries use."""
        return self.original_size or (int(self.image.shape[1]), int(self.image.shape[0]))


InputKind = Literal["envelope", "image"]
# The first bytes of the image files OpenCV reads. None of them can start a msgpack map (an envelope): JPEG's
# 0xFF and the ASCII letters are integers in msgpack, and PNG's 0x89 (a map of 9 entries) is followed by 'P',
# an integer where a map needs a string key. So a signature decides even against a wrong zenoh encoding.
IMAGE_SIGNATURES = (
    (b"\x89PNG", "PNG"),
    (b"\xff\xd8\xff", "JPEG"),
    (b"BM", "BMP"),
    (b"GIF87a", "GIF"),
    (b"GIF89a", "GIF"),
    (b"II*\x00", "TIFF"),
    (b"MM\x00*", "TIFF"),
    (b"RIFF", "WebP"),
)


def image_format(payload: bytes) -> str | None:
    """The image file format ``payload`` starts with (PNG, JPEG, BMP, GIF, TIFF, WebP), or None."""
    return next((name for signature, name in IMAGE_SIGNATURES if payload.startswith(signature)), None)


def _starts_a_msgpack_map(payload: bytes) -> bool:
    return bool(payload) and (0x80 <= payload[0] <= 0x8F or payload[0] in (0xDE, 0xDF))


def input_kind(payload: bytes, encoding: str) -> InputKind:
    """What an input payload is: a bare image file or an ImageEnvelope (msgpack). The one rule of intake, the
    age peek (service/runtime/intake/frame_age.py) and the decoder: an image file's signature first (it cannot start
    an envelope, so it wins over a wrong encoding), then the zenoh encoding when set (``image/*`` or
    ``application/msgpack``), then a msgpack map's first byte; anything else is taken as an image and the
    decoder says why it is not one."""
    if image_format(payload) is not None:
        return "image"
    mime = encoding.split(";", 1)[0].strip().lower()
    if mime.startswith("image/"):
        return "image"
    if mime == MSGPACK_ENCODING:
        return "envelope"
    return "envelope" if _starts_a_msgpack_map(payload) else "image"


def decode_payload(payload: bytes, encoding: str, received_at: float, max_bytes: int, max_pixels: int) -> DecodedFrame:
    """A bare image file or an ImageEnvelope (msgpack), told apart by ``input_kind``."""
    if len(payload) > max_bytes:
        raise RejectedInput("oversized", f"{len(payload)} bytes exceeds the limit of {max_bytes}")
    if not payload:
        raise RejectedInput("empty", "payload has 0 bytes")
    if input_kind(payload, encoding) == "envelope":
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
    for width, height in ((envelope.width, envelope.height), envelope.original_size or (1, 1)):
        if width * height > max_pixels:  # an original size is a geometry: full-resolution maps are made at it
            raise RejectedInput("too_many_pixels", f"{width}x{height} exceeds the limit of {max_pixels} pixels")
    if envelope.encoding in RAW_CHANNELS:
        image = _raw_pixels(envelope)
    else:
        try:
            image = decode_image(envelope.data, max_pixels)
        except ImageDecodeError as err:
            raise RejectedInput(err.reason, f"envelope {envelope.encoding.value}: {err}") from None
    return DecodedFrame(image, envelope.stamp, envelope.frame_id, envelope.original_size)


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
