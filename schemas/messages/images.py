"""Images in: a camera frame with its capture stamp, as the client library and the relay publish it."""

from __future__ import annotations

from enum import Enum

from gcdtrav.schemas.limits import MAX_FRAME_ID_CHARS
from gcdtrav.schemas.messages.base import Message
from pydantic import Field, field_validator


class PixelEncoding(str, Enum):
    RGB8 = "rgb8"
    BGR8 = "bgr8"
    MONO8 = "mono8"
    JPEG = "jpeg"
    PNG = "png"


RAW_CHANNELS = {PixelEncoding.RGB8: 3, PixelEncoding.BGR8: 3, PixelEncoding.MONO8: 1}


class ImageEnvelope(Message):
    """An image with its capture time and camera frame, as the client library publishes it."""

    stamp: float = Field(description="Capture time, seconds since the Unix epoch.")
    frame_id: str = Field(
        default="",
        max_length=MAX_FRAME_ID_CHARS,
        description="The camera's coordinate frame, passed through to the maps.",
    )
    encoding: PixelEncoding
    width: int = Field(ge=1)
    height: int = Field(ge=1)
    data: bytes = Field(description="Row-major pixels (raw encodings) or the compressed file (jpeg, png).")
    sent_at: float | None = Field(
        default=None,
        description="When the sender published it, its own clock (a relay sets it): echoed in the credit, so the "
        "sender can estimate the link's round trip and the clock offset.",
    )
    original_size: tuple[int, int] | None = Field(
        default=None,
        description="(width, height) of the camera's image when the sender shrank it (a relay does): the maps' "
        "geometry and the answers' pixels are in it. None: the image is the camera's. Since 1.2.",
    )

    @field_validator("original_size")
    @classmethod
    def _positive_size(cls, value: tuple[int, int] | None) -> tuple[int, int] | None:
        if value is not None and min(value) < 1:
            raise ValueError(f"{value} must be (width, height), each at least 1")
        return value
