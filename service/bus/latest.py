"""Latest-only, round-robin frame queue: one pending slot per source.

A robot publishes faster than a CPU infers. Keeping only the newest unprocessed frame per source bounds
memory (sources x one payload) whatever the input rate, and serving sources in turn keeps one fast
robot from starving the others.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Generic, TypeVar

T = TypeVar("T")


@dataclass
class QueueCounters:
    received: int = 0
    dropped: int = 0  # replaced by a newer frame before it was taken


@dataclass
class LatestFrameQueue(Generic[T]):
    _pending: OrderedDict[str, T] = field(default_factory=OrderedDict)
    _counters: dict[str, QueueCounters] = field(default_factory=dict)
    _cond: threading.Condition = field(default_factory=threading.Condition)
    _closed: bool = False

    def put(self, source: str, item: T) -> bool:
        """Store ``item`` as the source's newest frame. Returns False if it replaced (dropped) an older one."""
        with self._cond:
            counters = self._counters.setdefault(source, QueueCounters())
            counters.received += 1
            replaced = source in self._pending
            if replaced:
                counters.dropped += 1
            # A replaced item keeps the source's place in the rotation; a new one joins at the back.
            self._pending[source] = item
            self._cond.notify()
            return not replaced

    def count_unqueued(self, source: str) -> None:
        """Count a frame that was received but refused before queueing (e.g. over the byte limit)."""
        with self._cond:
            self._counters.setdefault(source, QueueCounters()).received += 1

    def take(self, timeout: float | None = None) -> tuple[str, T] | None:
        """The oldest-waiting source's newest frame; None on timeout or after close()."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._pending or self._closed, timeout):
                return None
            if not self._pending:
                return None
            return self._pending.popitem(last=False)

    def forget(self, source: str) -> None:
        """Drop the source's pending frame and counters (a source the service no longer tracks)."""
        with self._cond:
            self._pending.pop(source, None)
            self._counters.pop(source, None)

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def __len__(self) -> int:
        with self._cond:
            return len(self._pending)

    def counters(self) -> dict[str, QueueCounters]:
        with self._cond:
            return {s: QueueCounters(c.received, c.dropped) for s, c in self._counters.items()}
