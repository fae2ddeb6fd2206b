"""How old a frame is when it reaches the service, read without decoding it; which frames are too old.

After an outage a link delivers what it buffered: frames seconds old, whose maps describe where the robot
was. The service drops a frame captured more than ``max_frame_age_s`` ago, at intake and again before
inference, and counts it as ``stale``.

Clocks: the age is the service's clock minus the capture stamp, which the robot's clock wrote (an envelope's
``stamp``, a ROS header). It assumes both clocks in step (NTP, chrony) to well within ``max_frame_age_s``; a
robot ahead shows negative ages, one behind by more than the limit has every frame dropped (the status's
``frame_age_ms`` shows either). Robots on simulated time: ``max_frame_age_s: null``. Bare JPEG/PNG inputs
carry no stamp: their age is 0 at intake.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

from gcdtrav.schemas.inputs import input_kind
from gcdtrav.schemas.messages import MessageError, peek_fields


@dataclass(frozen=True)
class InputTimes:
    stamp: float | None  # capture; None: a bare image, or unreadable (the decoder will say why)
    sent_at: float | None  # the envelope's sent_at (a relay's clock)


def _number(value: object) -> float | None:
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None


def ros_header_stamp(payload: bytes) -> float | None:
    """The header stamp of a stamped ROS message in CDR (the header comes first: int32 sec, uint32 nanosec
    after the 4-byte encapsulation header); None when the payload is too short or not CDR."""
    if len(payload) < 12 or payload[0] != 0 or payload[1] not in (0, 1):
        return None
    sec, nanosec = struct.unpack_from("<iI" if payload[1] == 1 else ">iI", payload, 4)
    return sec + nanosec * 1e-9


def envelope_times(payload: bytes) -> InputTimes:
    try:
        fields = peek_fields(payload, ("stamp", "sent_at"))
    except MessageError:
        return InputTimes(None, None)
    return InputTimes(_number(fields.get("stamp")), _number(fields.get("sent_at")))


def input_times(payload: bytes, encoding: str, ros: bool) -> InputTimes:
    """Capture stamp and send time of an input payload, as cheaply as possible (no pixels are touched)."""
    if ros:
        return InputTimes(ros_header_stamp(payload), None)
    return envelope_times(payload) if input_kind(payload, encoding) == "envelope" else InputTimes(None, None)


class FrameAgeLimit:
    """``max_frame_age_s`` (None: no limit). A frame exactly at the limit is kept; an unknown or non-finite
    stamp never makes a frame stale (the decoder rejects what is unreadable)."""

    def __init__(self, max_age_s: float | None) -> None:
        if max_age_s is not None and not max_age_s > 0:
            raise ValueError(f"max_frame_age_s must be positive or None, got {max_age_s}")
        self.max_age_s = max_age_s

    def age_s(self, stamp: float | None, now: float) -> float | None:
        return now - stamp if stamp is not None and math.isfinite(stamp) else None

    def is_stale(self, stamp: float | None, now: float) -> bool:
        age = self.age_s(stamp, now)
        return self.max_age_s is not None and age is not None and age > self.max_age_s

    def explain(self, stamp: float | None, now: float) -> str:
        """Why a frame is stale, with what to check."""
        return (
            f"captured {self.age_s(stamp, now) or 0:.1f} s ago, over max_frame_age_s = {self.max_age_s:g} s "
            "(robot and service clocks out of step, or replayed data? max_frame_age_s: null turns the limit off)"
        )
