"""Which sources the service keeps state for: a bounded set, idle ones forgotten. No middleware here.

A source is a name taken from an input key, so any peer can invent new ones (a robot that puts every frame
under a new name, a hostile host on the LAN). Everything the service keeps per source (pending frame,
history, counters, publishers) is kept only for admitted sources: at most ``max_sources`` at once, each
forgotten after ``idle_s`` without a frame. A new source beyond the cap is refused; an active source is
never evicted to make room.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable

SWEEP_INTERVAL_S = 1.0


class SourceTracker:
    def __init__(
        self,
        max_sources: int,
        idle_s: float,
        on_forget: Iterable[Callable[[str], None]] = (),
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.max_sources = max_sources
        self.idle_s = idle_s
        self._on_forget = list(on_forget)
        self._clock = clock
        self._last_seen: dict[str, float] = {}
        self._next_sweep = clock() + SWEEP_INTERVAL_S
        self._lock = threading.Lock()

    def admit(self, source: str) -> bool:
        """Note a frame from ``source``; False if it is new and the cap is reached."""
        with self._lock:
            if source not in self._last_seen and len(self._last_seen) >= self.max_sources:
                return False
            self._last_seen[source] = self._clock()
            return True

    def sweep(self) -> list[str]:
        """Forget the sources idle for longer than ``idle_s`` (checked at most once a second)."""
        now = self._clock()
        with self._lock:
            if now < self._next_sweep:
                return []
            self._next_sweep = now + SWEEP_INTERVAL_S
            idle = [source for source, seen in self._last_seen.items() if now - seen > self.idle_s]
            for source in idle:
                del self._last_seen[source]
        for source in idle:  # outside the lock: forgetting may undeclare publishers
            for forget in self._on_forget:
                forget(source)
        return idle

    def __len__(self) -> int:
        with self._lock:
            return len(self._last_seen)

    def __contains__(self, source: object) -> bool:
        with self._lock:
            return source in self._last_seen
