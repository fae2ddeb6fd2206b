"""Each source's clock, learnt from what arrives: no clock is assumed in step with the service's. No middleware.

A frame's *delay* is its receipt here minus its capture stamp (the robot's clock): the clock offset (service
minus robot) plus the time it took to get here. The smallest delay of a source's recent frames is
offset + the link's smallest delay, so a frame's *lag*, its delay beyond that smallest one, is how much
longer than the fastest frame it took: the age ``max_frame_age_s`` judges under ``clock: estimated``, whatever
the two clocks read (service/runtime/intake/freshness.py). Learnt per source:

- The smallest delay of the fresh frames of the last ``WINDOW_S`` of streaming (schemas/delay_window.py, the
  window a grid's pose stream and a relay's camera clock learn by too): a new smallest one at once (a faster
  frame, or the robot's clock stepped forward), a larger one as older frames leave the window (drift, a small
  step back). Frames judged stale never enter it, and the window's time runs only while fresh frames flow (a
  gap counts ``GAP_S`` at most): a backlog after an outage of any length is judged against the clock learnt
  before it.
- A clock step larger than the limits: a run of consecutive frames beyond ``max_frame_age_s`` (the clock
  stepped back) or ahead by more than ``max_stamp_skew_s`` (stepped forward far) is a step when its smallest
  delay stops falling: held within ``FLAT_S`` for ``STEP_HOLD_S`` and ``STEP_FRAMES`` frames, the source's
  clock is learnt again from the run. A backlog draining is not a step: each frame waited less than the one
  before, so the run's smallest delay keeps falling (by more than ``FLAT_S`` a second unless the link
  drains slower than 1.05 times the frame rate).

What this cannot tell apart: a delay that stays high (a standing queue on the link) from a clock that
stepped back; both are learnt, within ``WINDOW_S`` or, beyond ``max_frame_age_s``, ``STEP_HOLD_S``.
``clock: synced`` judges such frames by the service's clock.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field

from gcdtrav.schemas.delay_window import SmallestDelay

STEP_HOLD_S = 1.0  # a run's smallest delay held this long is a clock step
STEP_FRAMES = 3  # ... over at least this many frames
FLAT_S = 0.05  # a run's smallest delay falling by more than this is a backlog draining
WARN_OFFSET_S = 1.0  # warned once per source beyond this offset

BEHIND, AHEAD = "behind", "ahead"  # a run of frames: older than max_frame_age_s / stamped far ahead


@dataclass(frozen=True)
class Reading:
    """One frame against its source's clock."""

    lag_s: float  # delay beyond the source's smallest recent one (0: as fast as the fastest)
    offset_s: float  # the estimate after this frame: service minus robot clock plus the link's smallest delay
    stepped_s: float = 0.0  # nonzero: this frame confirmed a clock step of this much (the estimate moved)
    first_large_offset: bool = False  # the first time this source's offset exceeds WARN_OFFSET_S


@dataclass
class _Run:
    """Consecutive frames on one side of the accepted band, waiting to prove a clock step."""

    side: str
    floor: float  # their smallest delay
    since: float  # receipt of the frame that last lowered the floor by more than FLAT_S
    reference: float  # the floor then
    frames: int  # frames since then


@dataclass
class _SourceClock:
    offset: float  # the window's smallest delay, or a confirmed step's
    window: SmallestDelay = field(default_factory=SmallestDelay)
    run: _Run | None = None
    warned: bool = False

    def learn(self, received_at: float, delay: float) -> None:
        """A fresh frame: the window's smallest delay is the estimate."""
        smallest = self.window.add(received_at, delay)
        self.offset = delay if smallest is None else smallest  # None only for a non-finite delay, never here
        self.run = None

    def extend_run(self, side: str, received_at: float, delay: float) -> float:
        """A frame beyond the band; the step it confirms (0.0: none yet)."""
        run = self.run
        if run is None or run.side != side:
            self.run = _Run(side, delay, received_at, delay, 1)
            return 0.0
        run.floor = min(run.floor, delay)
        if delay < run.reference - FLAT_S:
            run.since, run.reference, run.frames = received_at, delay, 1
            return 0.0
        run.frames += 1
        if received_at - run.since < STEP_HOLD_S or run.frames < STEP_FRAMES:
            return 0.0
        stepped = run.floor - self.offset
        self.offset = run.floor
        self.window.restart(received_at, run.floor)
        self.run = None
        return stepped


class ClockOffsets:
    """Per tracked source; thread-safe (subscriber callbacks)."""

    def __init__(self, max_lag_s: float | None, max_ahead_s: float | None) -> None:
        self.max_lag_s, self.max_ahead_s = max_lag_s, max_ahead_s
        self._clocks: dict[str, _SourceClock] = {}
        self._lock = threading.Lock()

    def observe(self, source: str, stamp: float, received_at: float) -> Reading:
        """Judge a frame stamped ``stamp`` (finite) received at ``received_at`` against its source's clock, and
        learn from it. The first frame of a source sets its clock (lag 0)."""
        delay = received_at - stamp
        with self._lock:
            clock = self._clocks.get(source)
            if clock is None:
                clock = self._clocks[source] = _SourceClock(delay)
            lag = delay - clock.offset
            side = self._side(lag)
            stepped = 0.0
            if side is None:
                clock.learn(received_at, delay)
            else:
                stepped = clock.extend_run(side, received_at, delay)
            warn = not clock.warned and abs(clock.offset) > WARN_OFFSET_S
            clock.warned |= warn
            return Reading(delay - clock.offset, clock.offset, stepped, warn)

    def _side(self, lag: float) -> str | None:
        if self.max_lag_s is not None and lag > self.max_lag_s:
            return BEHIND
        if self.max_ahead_s is not None and lag < -self.max_ahead_s:
            return AHEAD
        return None

    def offsets(self) -> dict[str, float]:
        with self._lock:
            return {source: clock.offset for source, clock in self._clocks.items()}

    def forget(self, source: str) -> None:
        with self._lock:
            self._clocks.pop(source, None)


def usable_stamp(stamp: float | None) -> bool:
    """A stamp that can teach a clock: a finite, non-negative time (anything else is rejected as bad_stamp)."""
    return stamp is not None and math.isfinite(stamp) and stamp >= 0
