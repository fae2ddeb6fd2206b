"""The smallest-delay window: how the service and a robot's relay learn a clock they do not share. No I/O.

A sample's *delay*, its receipt on this clock minus its stamp on the other, is the clock offset plus the time
it took; the smallest recent one is the offset plus the link's smallest delay. One window for the three
learners, so they cannot learn apart: a source's clock at intake (service/runtime/intake/clock_offset.py adds
the clock steps), a grid's pose stream (service/grid/poses.py) and a relay's camera (client/relay/state.py).
The window is ``WINDOW_S`` of *streaming*: a gap counts ``GAP_S`` at most, a receipt before the last none, so
an outage ages nothing out and the backlog after it is judged by the clock learnt before it. A new smallest
delay is learnt at once (a faster sample, a clock stepped forward), a larger one as older samples leave.
"""

from __future__ import annotations

import math
from collections import deque

WINDOW_S = 30.0  # the smallest delay of this much streaming is the estimate
GAP_S = 1.0  # a gap between samples counts at most this much of the window


class SmallestDelay:
    """The smallest delay of the last ``window_s`` of streaming. Not thread-safe: its owner's lock guards it."""

    def __init__(self, window_s: float = WINDOW_S, gap_s: float = GAP_S) -> None:
        self.window_s, self.gap_s = window_s, gap_s
        self._samples: deque[tuple[float, float]] = deque()  # (streamed, delay), delays increasing
        self._streamed = 0.0  # seconds of streaming so far: the window's time
        self._last: float | None = None  # the last sample's receipt

    @property
    def smallest(self) -> float | None:
        """Receipt clock minus stamp clock plus the link's smallest delay; None before a sample."""
        return self._samples[0][1] if self._samples else None

    def add(self, received_at: float, delay: float) -> float | None:
        """Learn a sample received at ``received_at`` (this clock) ``delay`` after its stamp; a non-finite one
        (an unknown receipt or stamp) teaches nothing. The smallest delay now."""
        if not (math.isfinite(received_at) and math.isfinite(delay)):
            return self.smallest
        if self._last is not None:
            self._streamed += min(max(received_at - self._last, 0.0), self.gap_s)
        self._last = received_at
        while self._samples and self._samples[-1][1] >= delay:
            self._samples.pop()  # never the smallest again while this one is in the window
        self._samples.append((self._streamed, delay))
        while self._samples[0][0] < self._streamed - self.window_s:
            self._samples.popleft()  # never the sample just added
        return self._samples[0][1]

    def restart(self, received_at: float, delay: float) -> None:
        """Learn the clock afresh from one sample: the other clock stepped (confirmed by the caller)."""
        self._samples.clear()
        self._last = None
        self.add(received_at, delay)


def clock_difference(offset_a: float | None, offset_b: float | None) -> float | None:
    """Clock b minus clock a, from two windows' smallest delays on one receiving clock (a's and b's offsets),
    within the difference of their links' smallest delays (a's minus b's); None while either is unknown."""
    return None if offset_a is None or offset_b is None else offset_a - offset_b
