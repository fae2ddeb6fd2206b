"""A frame's capture stamp and send time, read without decoding it (no pixels are touched).

The stamp is the robot's clock (an envelope's ``stamp``, a ROS header's); how old that makes the frame is
service/runtime/freshness.py's to judge. Bare JPEG/PNG inputs carry no stamp: their age is the time since
their receipt.
"""

from __future__ import annotations

from dataclasses import dataclass

from gcdtrav.schemas.inputs import input_kind
from gcdtrav.schemas.messages import MessageError, peek_fields
from gcdtrav.schemas.ros_image import peek_stamp


@dataclass(frozen=True)
class InputTimes:
    stamp: float | None  # capture; None: a bare image, or unreadable (the decoder will say why)
    sent_at: float | None  # the envelope's sent_at (a relay's clock)


def _number(value: object) -> float | None:
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None


def envelope_times(payload: bytes) -> InputTimes:
    try:
        fields = peek_fields(payload, ("stamp", "sent_at"))
    except MessageError:
        return InputTimes(None, None)
    return InputTimes(_number(fields.get("stamp")), _number(fields.get("sent_at")))


def input_times(payload: bytes, encoding: str, ros: bool) -> InputTimes:
    """Capture stamp and send time of an input payload, as cheaply as possible (no pixels are touched)."""
    if ros:
        return InputTimes(peek_stamp(payload), None)
    return envelope_times(payload) if input_kind(payload, encoding) == "envelope" else InputTimes(None, None)
