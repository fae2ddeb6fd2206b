"""How old the newest maps of each source are, and when they became stale: no zenoh, a clock given.

Ages compare the maps' capture stamp with this machine's clock. On the robot that captured the image both
are the robot's clock, so the age is exact; elsewhere it assumes clocks in step (NTP, chrony), and is off by
their offset otherwise. A caller that knows the offset passes stamps on its own clock: the relay adds the
camera's learnt offset (client/relay/state.py CameraClock).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class Staleness:
    """A change of one source's state: stale (no maps newer than the limit) or fresh again."""

    source: str
    stale: bool
    age_s: float  # of the newest maps when the change was seen; before any, the time since they were expected
    reason: str | None = None  # why the service gives no maps, as it last said (a credit's problem), if it did


class FreshnessWatch:
    """Thread-safe: ``observe`` from subscriber callbacks, ``check`` from a timer."""

    def __init__(self, stale_after_s: float, clock: Callable[[], float] = time.time) -> None:
        if not stale_after_s > 0:
            raise ValueError(f"stale_after_s must be positive, got {stale_after_s}")
        self.stale_after_s = stale_after_s
        self._clock = clock
        self._newest: dict[str, float] = {}
        self._since: dict[str, float] = {}  # when a watched source began to be expected
        self._stale: dict[str, bool] = {}
        self._reasons: dict[str, str | None] = {}
        self._told: dict[str, str | None] = {}  # the reason of each source's last reported change
        self._lock = threading.Lock()

    def watch(self, source: str, since: float | None = None) -> None:
        """Expect maps of ``source`` from ``since`` (default now): without any, it goes stale
        ``stale_after_s`` later (its age counts from ``since``; ``newest`` stays None)."""
        with self._lock:
            self._since.setdefault(source, self._clock() if since is None else since)
            self._newest.setdefault(source, -math.inf)
            self._stale.setdefault(source, False)

    def observe(self, source: str, stamp: float) -> None:
        """Maps (or a grid) of ``source`` captured at ``stamp`` arrived; older ones than known change nothing."""
        if not math.isfinite(stamp):
            return
        with self._lock:
            self._newest[source] = max(self._newest.get(source, -math.inf), stamp)
            self._stale.setdefault(source, False)

    def note_reason(self, source: str, reason: str | None) -> None:
        """What the service last said of ``source``'s frames (None: nothing wrong); changes report it."""
        with self._lock:
            self._reasons[source] = reason

    def reason(self, source: str) -> str | None:
        with self._lock:
            return self._reasons.get(source)

    def newest(self, source: str) -> float | None:
        with self._lock:
            stamp = self._newest.get(source, -math.inf)
        return stamp if math.isfinite(stamp) else None

    def age_s(self, source: str) -> float:
        """Now minus the newest maps' stamp; before any, the time since the source was watched (inf if not)."""
        with self._lock:
            return self._clock() - self._reference(source)

    def _reference(self, source: str) -> float:
        newest = self._newest.get(source, -math.inf)
        return newest if math.isfinite(newest) else self._since.get(source, -math.inf)

    def is_stale(self, source: str) -> bool:
        return self.age_s(source) > self.stale_after_s

    def check(self) -> list[Staleness]:
        """The sources whose state changed since the last check (stale, or fresh again), and stale ones whose
        reason changed (the service named one only after they went stale, or another)."""
        now = self._clock()
        changes = []
        with self._lock:
            for source in self._newest:
                age = now - self._reference(source)
                stale = age > self.stale_after_s
                reason = self._reasons.get(source) if stale else None
                if stale != self._stale[source] or (stale and reason != self._told.get(source)):
                    self._stale[source] = stale
                    self._told[source] = reason
                    changes.append(Staleness(source, stale, age, reason))
        return changes
