"""Which sources the service keeps state for: a bounded set, idle ones forgotten. No middleware here.

A source is a name taken from an input key, so any peer can invent new ones (a robot that puts every frame
under a new name, a hostile host on the LAN). Everything the service keeps per source (pending frame,
history, counters, publishers) is kept only for admitted sources: at most ``max_sources`` at once, each
forgotten after ``idle_s`` without a frame. A source is admitted (``promote``) only once one of its frames
decoded (service/runtime/intake/candidates.py holds it until then). When the set is full, the slot of a source
that sent a single frame and has been idle for ``reclaim_after_s`` is reclaimed, the idlest first (a flood
of one-frame names that did decode); a source with two frames or more is never evicted to make room.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable

SWEEP_INTERVAL_S = 1.0


class SourcesFull(Exception):
    """Every slot is taken by a source that cannot be reclaimed."""


class SourceTracker:
    def __init__(
        self,
        max_sources: int,
        idle_s: float,
        on_forget: Iterable[Callable[[str], None]] = (),
        clock: Callable[[], float] = time.monotonic,
        reclaim_after_s: float = 2.0,
    ) -> None:
        self.max_sources = max_sources
        self.idle_s = idle_s
        self.reclaim_after_s = reclaim_after_s
        self._on_forget = list(on_forget)
        self._clock = clock
        self._last_seen: dict[str, float] = {}
        self._frames: dict[str, int] = {}  # frames noted since admission: 1 marks a reclaimable slot
        self._publisher: dict[str, str | None] = {}
        self._next_sweep = clock() + SWEEP_INTERVAL_S
        self._lock = threading.Lock()

    def note(self, source: str) -> bool:
        """Note a frame from a tracked ``source``; False (nothing noted) if it is not tracked."""
        with self._lock:
            if source not in self._last_seen:
                return False
            self._last_seen[source] = self._clock()
            self._frames[source] += 1
            return True

    def promote(self, source: str, publisher: str | None = None) -> str | None:
        """Track ``source`` (its frame decoded), reclaiming a one-frame slot if full; the source evicted for it,
        ``source`` itself if already tracked, or None; raises SourcesFull if no slot can be reclaimed."""
        with self._lock:
            if source in self._last_seen:
                return source
            evicted = self._reclaimable() if len(self._last_seen) >= self.max_sources else None
            if len(self._last_seen) >= self.max_sources and evicted is None:
                raise SourcesFull(f"'{source[:200]}': already tracking {self.max_sources} sources")
            if evicted is not None:
                self._drop(evicted)
            self._last_seen[source], self._frames[source], self._publisher[source] = self._clock(), 1, publisher
        if evicted is not None:
            self._run_forget(evicted)
        return evicted

    def can_reclaim(self) -> bool:
        """Whether a new source could be promoted now (a free slot or a reclaimable one)."""
        with self._lock:
            return len(self._last_seen) < self.max_sources or self._reclaimable() is not None

    def of_publisher(self, publisher: str) -> int:
        with self._lock:
            return sum(1 for who in self._publisher.values() if who == publisher)

    def _reclaimable(self) -> str | None:
        """The idlest source with a single frame, idle for at least reclaim_after_s."""
        now = self._clock()
        singles = [(seen, s) for s, seen in self._last_seen.items() if self._frames[s] == 1]
        seen, source = min(singles, default=(now, None))
        return source if now - seen >= self.reclaim_after_s else None

    def _drop(self, source: str) -> None:
        del self._last_seen[source], self._frames[source], self._publisher[source]

    def _run_forget(self, source: str) -> None:
        for forget in self._on_forget:
            forget(source)

    def forget_untracked(self, source: str) -> None:
        """Forget the state a source that is not tracked left behind (a candidate refused or evicted)."""
        if source not in self:
            self._run_forget(source)

    def sweep(self) -> list[str]:
        """Forget the sources idle for longer than ``idle_s`` (checked at most once a second)."""
        now = self._clock()
        with self._lock:
            if now < self._next_sweep:
                return []
            self._next_sweep = now + SWEEP_INTERVAL_S
            idle = [source for source, seen in self._last_seen.items() if now - seen > self.idle_s]
            for source in idle:
                self._drop(source)
        for source in idle:  # outside the lock: forgetting may undeclare publishers
            self._run_forget(source)
        return idle

    def __len__(self) -> int:
        with self._lock:
            return len(self._last_seen)

    def __contains__(self, source: object) -> bool:
        with self._lock:
            return source in self._last_seen
