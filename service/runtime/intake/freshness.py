"""Which frames may still become maps: stamps that mean something, sources still owned, frames not too old.
The one place ``max_frame_age_s``, ``max_stamp_skew_s`` and ``clock`` are judged. No middleware here.

A frame's age is its *lag* at intake plus the time since its receipt here:

- ``clock: estimated`` (default): the lag is its delay beyond its source's smallest recent delay
  (service/runtime/intake/clock_offset.py), whatever the robot's clock reads; a robot whose clock is off by seconds
  or years is served, a link's backlog after an outage is still dropped.
- ``clock: synced``: the lag is the service's clock minus the capture stamp, for fleets that guarantee NTP;
  a robot whose clock is off has its frames dropped ``stale`` (behind) or rejected ``skewed_stamp`` (ahead).

A negative lag (a robot clock slightly ahead under ``synced``) ages nothing: the receipt still does. Judged
at intake (``Freshness.at_intake``: the lag, read without decoding, and the skew), before inference and just
before publishing (``FrameGate``): inference may have taken long (a hung worker, a SIGSTOP), or the source
moved to another instance meanwhile. Every frame stopped here is counted by reason: rejected ``bad_stamp`` /
``skewed_stamp``, dropped ``stale`` / ``not_owner``.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

from gcdtrav.schemas.inputs import DecodedFrame, RejectedInput
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.runtime.frames import PendingFrame
from gcdtrav.service.runtime.intake.clock_offset import ClockOffsets, Reading, usable_stamp

ClockMode = Literal["estimated", "synced"]
WARN_INTERVAL_S = 5.0


class Dropped(Exception):
    """A good frame that will not be published; ``reason`` is its code in ``dropped_by_reason``."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


def _age(lag_s: float | None, waited_s: float) -> float:
    """The lag at intake (a negative one, a clock slightly ahead, ages nothing) plus the time waited here."""
    return max(lag_s or 0.0, 0.0) + waited_s


def check_stamp(stamp: float) -> None:
    """A stamp that is a finite, non-negative time: anything else says nothing about when or in what order."""
    if not math.isfinite(stamp) or stamp < 0:
        raise RejectedInput("bad_stamp", f"stamp {stamp!r} is not a time")


@dataclass(frozen=True)
class IntakeAge:
    lag_s: float | None  # None: no usable stamp (its age is the time since its receipt)
    refusal: RejectedInput | Dropped | None  # skewed_stamp, stale; None: to be queued


class Freshness:
    """The age rule: thread-safe (subscriber callbacks judge at intake, workers later)."""

    def __init__(
        self,
        max_age_s: float | None,
        max_skew_s: float | None,
        clock: ClockMode = "estimated",
        log: logging.Logger | None = None,
    ) -> None:
        if max_age_s is not None and not max_age_s > 0:
            raise ValueError(f"max_frame_age_s must be positive or None, got {max_age_s}")
        self.max_age_s, self.max_skew_s, self.clock = max_age_s, max_skew_s, clock
        self.offsets = ClockOffsets(max_age_s, max_skew_s)
        self._log = log or logging.getLogger("gcdtrav.service")
        self._warned_at = -math.inf
        self._warn_lock = threading.Lock()

    @classmethod
    def from_settings(cls, settings: ServiceSettings, log: logging.Logger | None = None) -> Freshness:
        return cls(settings.max_frame_age_s, settings.max_stamp_skew_s, settings.clock, log)

    def at_intake(self, source: str, stamp: float | None, received_at: float) -> IntakeAge:
        """The frame's lag and, if it is not to be queued, why; its source's clock learns from it (the first
        frame of a source sets it: lag 0 under estimated). The clock is forgotten with the source, or with a
        new source that is refused (``SourceTracker``'s forget callbacks)."""
        if not usable_stamp(stamp):
            return IntakeAge(None, None)  # a bare image, or a stamp the decoder rejects (bad_stamp)
        assert stamp is not None
        reading = self._observe(source, stamp, received_at)
        lag = received_at - stamp if self.clock == "synced" else reading.lag_s
        if self.max_skew_s is not None and lag < -self.max_skew_s:
            return IntakeAge(lag, RejectedInput("skewed_stamp", self._explain_skew(lag, reading)))
        try:
            self._check_age(lag, 0.0, "at intake", reading)
        except Dropped as stale:
            return IntakeAge(lag, stale)
        return IntakeAge(lag, None)

    def check(self, pending: PendingFrame, now: float, when: str) -> float:
        """The frame's age at ``now``; raise Dropped (``stale``) if it is older than max_frame_age_s."""
        return self._check_age(pending.lag_s, now - pending.received_at, when, None)

    def _check_age(self, lag_s: float | None, waited_s: float, when: str, reading: Reading | None) -> float:
        age = _age(lag_s, waited_s)
        if self.max_age_s is not None and age > self.max_age_s:
            raise Dropped("stale", self._explain_age(age, waited_s, when, reading))
        return age

    def _observe(self, source: str, stamp: float, received_at: float) -> Reading:
        reading = self.offsets.observe(source, stamp, received_at)
        if reading.stepped_s:
            self._log.warning(
                "%s: its clock stepped %+.3f s (learnt again; clock offset now %+.3f s)",
                source,
                -reading.stepped_s,
                reading.offset_s,
            )
        if reading.first_large_offset and self._may_warn():
            self._log.warning("%s: %s", source, self._offset_advice(reading.offset_s))
        return reading

    def _may_warn(self) -> bool:
        """At most one offset warning every WARN_INTERVAL_S, whatever the sources: new names with wrong clocks
        (each forgotten when refused, so warned again) cannot flood the log."""
        now = time.monotonic()
        with self._warn_lock:
            if now - self._warned_at < WARN_INTERVAL_S:
                return False
            self._warned_at = now
            return True

    def _offset_advice(self, offset_s: float) -> str:
        said = f"clock offset {offset_s:+.3f} s (service minus robot, plus the link's smallest delay)"
        if self.clock == "synced":
            return (
                f"{said}: with clock: synced its frames are judged by the service's clock and dropped stale or "
                "rejected skewed_stamp; sync its clock (NTP, chrony) or set clock: estimated"
            )
        return f"{said}: its frames are judged by their delay (clock: estimated); its maps keep its stamps"

    def _explain_age(self, age: float, waited_s: float, when: str, reading: Reading | None) -> str:
        limit = f"over max_frame_age_s = {self.max_age_s:g} s"
        if when != "at intake":
            why = "a stalled or frozen instance, or slow inference"
            return f"{age:.1f} s old {when} ({waited_s:.1f} s here), {limit} ({why})"
        if self.clock == "synced":
            return (
                f"captured {age:.1f} s ago by the service's clock, {limit} (robot clock behind? clock: estimated "
                "judges by delay; replayed data? max_frame_age_s: null)"
            )
        offset = f", clock offset {reading.offset_s:+.1f} s" if reading is not None else ""
        return f"{age:.1f} s slower than its source's fastest recent frame{offset}, {limit} (a link's backlog)"

    def _explain_skew(self, lag: float, reading: Reading) -> str:
        limit = f"(max_stamp_skew_s {self.max_skew_s:g})"
        if self.clock == "synced":
            return f"stamp {-lag:.1f} s ahead of its receipt {limit}: sync the robot's clock (NTP, chrony)"
        return (
            f"stamp {-lag:.1f} s ahead of its source's clock (offset {reading.offset_s:+.1f} s) {limit}: a step "
            "forward is learnt once it holds"
        )


class FrameGate:
    """Before inference and before publishing: a stamp that means something, the owner, the age."""

    def __init__(
        self, owns: Callable[[str], bool], freshness: Freshness, clock: Callable[[], float] = time.time
    ) -> None:
        self.owns, self.freshness = owns, freshness
        self._clock = clock

    def before_inference(self, pending: PendingFrame, image: DecodedFrame) -> None:
        """Raise RejectedInput for a meaningless stamp, Dropped for a frame not worth inferring."""
        check_stamp(image.stamp)
        self._check_owner(pending)
        self.freshness.check(pending, self._clock(), "before inference")

    def before_publish(self, pending: PendingFrame) -> float:
        """The frame's age as judged now (its maps' age when published: the metrics' map age); raise Dropped
        unless this instance owns the source now and the frame is young enough."""
        self._check_owner(pending)
        return self.freshness.check(pending, self._clock(), "when its maps were ready")

    def _check_owner(self, pending: PendingFrame) -> None:
        if not self.owns(pending.source):
            raise Dropped("not_owner", f"{pending.source} is served by another instance now")
