"""Which frames may still become maps: stamps that mean something, sources still owned, frames not too old.
No middleware here.

Checked after decoding (a bad stamp is rejected before inference; a frame no longer this instance's is
dropped without inference; ``frame_age.py`` drops one captured too long ago) and again just before
publishing: inference may have taken long (a hung worker, a SIGSTOP), or the source moved to another
instance meanwhile. An instance publishes only for the sources it owns at that moment, and only frames
younger than ``max_frame_age_s`` by the older of their stamp and their receipt here (the receipt also
ages bare images, whose stamp is their receipt, and frames of a robot whose clock runs ahead). Every frame
stopped here is counted by reason: rejected ``bad_stamp`` / ``skewed_stamp``, dropped ``stale`` /
``not_owner``.
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
    """A stamp that is a finite, non-negative time, at most ``max_skew_s`` ahead of its receipt (None: any).

    A stamp from the future would order a source's maps ahead of every later frame (``MapsHeader.order``);
    one from the past is what ``max_frame_age_s`` judges (off for simulated time)."""
    if not math.isfinite(stamp) or stamp < 0:
        raise RejectedInput("bad_stamp", f"stamp {stamp!r} is not a time")
    if max_skew_s is not None and stamp - received_at > max_skew_s:
        raise RejectedInput(
            "skewed_stamp",
            f"stamp {stamp:.3f} is {stamp - received_at:.1f} s ahead of its receipt (max_stamp_skew_s "
            f"{max_skew_s:g}): sync the robot's clock (NTP, chrony)",
        )


class FrameGate:
    def __init__(
        self,
        owns: Callable[[str], bool],
        max_frame_age_s: float | None,
        max_stamp_skew_s: float | None,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.owns, self.max_frame_age_s, self.max_stamp_skew_s = owns, max_frame_age_s, max_stamp_skew_s
        self._clock = clock

    def before_inference(self, pending: PendingFrame, image: DecodedFrame) -> None:
        """Raise RejectedInput for a meaningless stamp, Dropped for a frame not worth inferring."""
        check_stamp(image.stamp, pending.received_at, self.max_stamp_skew_s)
        self._check_owner(pending)

    def before_publish(self, pending: PendingFrame, stamp: float) -> None:
        """Raise Dropped unless this instance owns the source now and the frame is young enough."""
        self._check_owner(pending)
        if self.max_frame_age_s is None:
            return
        age_s = self._clock() - min(stamp, pending.received_at)
        if age_s > self.max_frame_age_s:
            raise Dropped(
                "stale",
                f"{age_s:.1f} s old when its maps were ready, over max_frame_age_s = {self.max_frame_age_s:g} s "
                "(a stalled or frozen instance, or inference slower than the limit)",
            )

    def _check_owner(self, pending: PendingFrame) -> None:
        if not self.owns(pending.source):
            raise Dropped("not_owner", f"{pending.source} is served by another instance now")
