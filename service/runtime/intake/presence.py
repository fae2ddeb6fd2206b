"""Which robots this instance has heard, when their last frame came and whether they parked a camera: what the
silent-robot alert reads (docs/metrics.md, "Robots heard, silent, parked"). No middleware here.

A source is *heard* by its frames on the inputs (every instance sees every source's frames, owner or not) and
by its relay's health over the link (``RelayHealth``, which also says ``parked``: the robot stopped that camera
on purpose). The alert compares the last frame's time with Prometheus's clock, so what it needs from here is a
wall-clock time, not an age: a forgotten source, or a restarted instance, leaves the alert its last value.

Bounded: at most ``capacity`` sources (the service's ``max_sources``); a new one beyond evicts the one heard
longest ago. A source heard of neither way for ``forget_after_s`` (``source_idle_s``) is forgotten.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

from gcdtrav.schemas.limits import MAX_SOURCE_CHARS


@dataclass(frozen=True)
class Heard:
    """One source as this instance heard it."""

    last_frame_at: float  # wall clock: its last frame here, or when its relay first spoke before any frame
    parked: bool | None  # its relay's last word (None: no relay health heard)


@dataclass
class _Entry:
    last_frame_at: float
    heard_at: float
    parked: bool | None = None


class SourcePresence:
    """Thread-safe: the subscriber callbacks note, the metrics read."""

    def __init__(self, capacity: int, forget_after_s: float, clock: Callable[[], float] = time.time) -> None:
        self.capacity, self.forget_after_s = capacity, forget_after_s
        self._clock = clock
        self._lock = threading.Lock()
        self._entries: OrderedDict[str, _Entry] = OrderedDict()  # heard longest ago first

    def frame(self, source: str) -> None:
        """A frame of ``source`` reached this instance (a name over MAX_SOURCE_CHARS is refused by the intake)."""
        if len(source) > MAX_SOURCE_CHARS:
            return
        now = self._clock()
        with self._lock:
            entry = self._entry(source, now)
            entry.last_frame_at = entry.heard_at = now

    def relay_health(self, source: str, parked: bool) -> None:
        """``source``'s relay spoke: the robot is there (its camera may still be silent), parked or not."""
        if len(source) > MAX_SOURCE_CHARS:
            return
        now = self._clock()
        with self._lock:
            entry = self._entry(source, now)  # a relay's first word starts the silence before any frame
            entry.heard_at, entry.parked = now, parked

    def heard(self) -> dict[str, Heard]:
        """Every source heard within ``forget_after_s``."""
        horizon = self._clock() - self.forget_after_s
        with self._lock:
            while self._entries and next(iter(self._entries.values())).heard_at < horizon:
                self._entries.popitem(last=False)
            return {name: Heard(e.last_frame_at, e.parked) for name, e in self._entries.items()}

    def _entry(self, source: str, now: float) -> _Entry:
        entry = self._entries.pop(source, None) or _Entry(last_frame_at=now, heard_at=now)
        self._entries[source] = entry  # heard now: the newest last
        while len(self._entries) > self.capacity:
            self._entries.popitem(last=False)
        return entry
