"""New sources waiting for a frame that decodes: *candidates*. No middleware here.

A source name costs nothing to invent, so a new name takes no slot of the SourceTracker until one of its
frames decodes (service/runtime/intake/sources.py). Until then its first frame waits in the queue like any other,
but candidates have their own small cap: a new one evicts the oldest, so a flood of invented names holds at
most ``max_candidates`` pending frames and never blocks a real robot's first frame for long.

The per-publisher cap counts, for one publisher (the zenoh session a sample came from, when the publisher
says so in its source info), the sources tracked and waiting; samples without a publisher are not capped.
"""

from __future__ import annotations

import threading
from collections import OrderedDict


class CandidatePool:
    """Waiting candidates (their frame queued; evictable) and taken ones (their frame being decoded)."""

    def __init__(self, max_candidates: int) -> None:
        self.max_candidates = max_candidates
        self._waiting: OrderedDict[str, str | None] = OrderedDict()  # source -> publisher, oldest first
        self._taken: dict[str, str | None] = {}  # at most one per worker: not evictable, counted once
        self._lock = threading.Lock()

    def add(self, source: str, publisher: str | None) -> str | None:
        """Wait for ``source``'s frame to decode; the oldest waiting candidate evicted to make room, if any."""
        with self._lock:
            if source in self._waiting or source in self._taken:
                return None
            evicted = None
            if len(self._waiting) >= self.max_candidates:
                evicted, _ = self._waiting.popitem(last=False)
            self._waiting[source] = publisher
            return evicted

    def take(self, source: str) -> None:
        """The worker took ``source``'s frame: no longer evictable (its outcome is counted once, by reason)."""
        with self._lock:
            if source in self._waiting:
                self._taken[source] = self._waiting.pop(source)

    def pop(self, source: str) -> tuple[bool, str | None]:
        """(whether it was a candidate, its publisher); it no longer is one."""
        with self._lock:
            for pool in (self._taken, self._waiting):
                if source in pool:
                    return True, pool.pop(source)
            return False, None

    def of_publisher(self, publisher: str) -> int:
        with self._lock:
            return sum(1 for pool in (self._waiting, self._taken) for who in pool.values() if who == publisher)

    def __contains__(self, source: object) -> bool:
        with self._lock:
            return source in self._waiting or source in self._taken

    def __len__(self) -> int:
        with self._lock:
            return len(self._waiting) + len(self._taken)


def over_publisher_cap(publisher: str | None, sources_of_publisher: int, cap: int | None) -> bool:
    """Whether one more source of ``publisher`` would exceed ``cap`` (no publisher or no cap: never)."""
    return publisher is not None and cap is not None and sources_of_publisher >= cap
