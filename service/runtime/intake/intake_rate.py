"""Intake work bounded per publisher: a token bucket per publishing session, checked before anything else a
frame costs (its key, its source, its payload). No middleware here: the bus hands over the publisher's id.

One process flooding names (or frames) costs the others a bounded share of the intake: beyond its rate its
frames are rejected ``rate_limited``, counted by reason only (a refused frame leaves no per-source state).
A publisher is the zenoh session its samples' source info names (client/source_info.py); samples without
source info (ROS bridges, plain zenoh puts) share one bucket, sized for a whole fleet behind a bridge.
A bucket that is full again holds nothing a new one would not: the oldest full ones are dropped when more
than ``MAX_PUBLISHERS`` publishers are known.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

MAX_PUBLISHERS = 4096


class TokenBucket:
    """``rate`` tokens a second, at most ``depth``; starts full."""

    __slots__ = ("depth", "rate", "tokens", "updated")

    def __init__(self, rate: float, depth: float, now: float) -> None:
        self.rate, self.depth, self.tokens, self.updated = rate, depth, depth, now

    def take(self, now: float) -> bool:
        self.tokens = min(self.depth, self.tokens + (now - self.updated) * self.rate)
        self.updated = now
        if self.tokens < 1.0:
            return False
        self.tokens -= 1.0
        return True

    def full_at(self, now: float) -> bool:
        return self.tokens + (now - self.updated) * self.rate >= self.depth


class IntakeRate:
    """Thread-safe (subscriber callbacks); ``admit`` is the cheapest check of the intake."""

    def __init__(
        self,
        per_publisher: float | None,
        anonymous: float | None,
        burst_s: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.per_publisher, self.burst_s, self._clock = per_publisher, burst_s, clock
        now = clock()
        self._anonymous = None if anonymous is None else TokenBucket(anonymous, max(1.0, anonymous * burst_s), now)
        self._buckets: dict[str, TokenBucket] = {}
        self._lock = threading.Lock()

    def admit(self, publisher: str | None) -> bool:
        """Whether a frame of ``publisher`` (None: no source info) may be looked at."""
        if publisher is None:
            if self._anonymous is None:
                return True
            with self._lock:
                return self._anonymous.take(self._clock())
        if self.per_publisher is None:
            return True
        with self._lock:
            now = self._clock()
            bucket = self._buckets.get(publisher)
            if bucket is None:
                if len(self._buckets) >= MAX_PUBLISHERS:
                    self._drop_full(now)
                bucket = self._buckets[publisher] = TokenBucket(
                    self.per_publisher, max(1.0, self.per_publisher * self.burst_s), now
                )
            return bucket.take(now)

    def _drop_full(self, now: float) -> None:
        """Under the lock: forget the buckets that are full again, else the least recently used half."""
        full = [who for who, bucket in self._buckets.items() if bucket.full_at(now)]
        if not full:
            by_use = sorted(self._buckets, key=lambda who: self._buckets[who].updated)
            full = by_use[: len(by_use) // 2 + 1]
        for who in full:
            del self._buckets[who]

    def __len__(self) -> int:
        with self._lock:
            return len(self._buckets)
