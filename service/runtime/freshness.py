"""Which frames may still become maps: stamps that mean something, frames not too old, sources still owned.
No middleware here.

Checked twice per frame: after decoding (a bad stamp is rejected before inference; a frame already too old or
no longer this instance's is dropped without inference) and just before publishing (inference may have taken
long, or the source moved to another instance meanwhile: an instance publishes only for the sources it owns
at that moment, and only frames younger than ``max_frame_age_s``). Every frame stopped here is counted by
reason: rejected ``bad_stamp`` / ``skewed_stamp``, dropped ``stale`` / ``not_owner``.

A frame's age is measured from its receipt on this host (``received_at``), not from its stamp: a robot's
clock may be off by seconds, this host's is the one that decides what is late here.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

from gcdtrav.schemas.inputs import DecodedFrame, RejectedInput
from gcdtrav.service.runtime.frames import PendingFrame


class Dropped(Exception):
    """A good frame that will not be published; ``reason`` is its code in ``dropped_by_reason``."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


def check_stamp(stamp: float, received_at: float, max_skew_s: float | None) -> None:
    """A stamp that is a finite, positive time within ``max_skew_s`` of the receipt (None: any finite one)."""
    if not math.isfinite(stamp) or stamp < 0:
        raise RejectedInput("bad_stamp", f"stamp {stamp!r} is not a time")
    if max_skew_s is not None and abs(stamp - received_at) > max_skew_s:
        raise RejectedInput(
            "skewed_stamp",
            f"stamp {stamp:.3f} is {stamp - received_at:+.1f} s from its receipt (max_stamp_skew_s {max_skew_s:g}; "
            "sync the robot's clock, or set max_stamp_skew_s: null for simulated time)",
        )


class FrameGate:
    def __init__(
        self,
        owns: Callable[[str], bool],
        max_frame_age_s: float,
        max_stamp_skew_s: float | None,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.owns, self.max_frame_age_s, self.max_stamp_skew_s = owns, max_frame_age_s, max_stamp_skew_s
        self._clock = clock

    def before_inference(self, pending: PendingFrame, image: DecodedFrame) -> None:
        """Raise RejectedInput for a meaningless stamp, Dropped for a frame not worth inferring."""
        check_stamp(image.stamp, pending.received_at, self.max_stamp_skew_s)
        self.before_publish(pending)

    def before_publish(self, pending: PendingFrame) -> None:
        """Raise Dropped unless this instance owns the source now and the frame is young enough."""
        if not self.owns(pending.source):
            raise Dropped("not_owner", f"{pending.source} is served by another instance now")
        age_s = self._clock() - pending.received_at
        if age_s > self.max_frame_age_s:
            raise Dropped("stale", f"received {age_s:.1f} s ago (max_frame_age_s {self.max_frame_age_s:g})")
