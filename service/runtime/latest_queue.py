"""Latest-only, round-robin frame queue: one pending slot per source.

A robot publishes faster than a CPU infers. Keeping only the newest unprocessed frame per source bounds
memory (sources x one payload) whatever the input rate, and serving sources in turn keeps one fast
robot from starving the others.

Sources whose first frame is waiting take at most every other turn while a returning source waits: a
flood of new names (a frame counter in the key, a hostile peer) then gets at most half of the inference,
and the robots that keep streaming the other half, instead of one turn in (flood + robots).
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


class PendingBudgetExceeded(Exception):
    """The frame would take the pending frames of all sources over the queue's byte budget."""


@dataclass
class LatestFrameQueue(Generic[T]):
    max_bytes: int | None = None  # all pending frames together; None: one frame per source is the only bound
    _pending: OrderedDict[str, tuple[T, int]] = field(default_factory=OrderedDict)
    _counters: dict[str, QueueCounters] = field(default_factory=dict)
    _cond: threading.Condition = field(default_factory=threading.Condition)
    _closed: bool = False
    _bytes: int = 0
    _last_took_new: bool = False

    def put(self, source: str, item: T, nbytes: int = 0) -> bool:
        """Store ``item`` as the source's newest frame. Returns False if it replaced (dropped) an older one.

        Raises PendingBudgetExceeded, keeping what is queued, if ``nbytes`` more would exceed ``max_bytes``.
        """
        with self._cond:
            counters = self._counters.setdefault(source, QueueCounters())
            counters.received += 1
            older = self._pending.get(source)
            freed = older[1] if older is not None else 0
            if self.max_bytes is not None and self._bytes - freed + nbytes > self.max_bytes:
                raise PendingBudgetExceeded(f"{nbytes} bytes would take the pending frames over {self.max_bytes} bytes")
            if older is not None:
                counters.dropped += 1
            # A replaced item keeps the source's place in the rotation; a new one joins at the back.
            self._pending[source] = (item, nbytes)
            self._bytes += nbytes - freed
            self._cond.notify()
            return older is None

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
            source = next(iter(self._pending))  # the oldest waiting
            if self._last_took_new and self._is_new(source):
                source = next((s for s in self._pending if not self._is_new(s)), source)
            self._last_took_new = self._is_new(source)
            item, nbytes = self._pending.pop(source)
            self._bytes -= nbytes
            return source, item

    def _is_new(self, source: str) -> bool:
        """Its first frame: nothing received from it before (forgotten sources start again)."""
        return self._counters[source].received == 1

    def forget(self, source: str) -> None:
        """Drop the source's pending frame and counters (a source the service no longer tracks)."""
        with self._cond:
            _, nbytes = self._pending.pop(source, (None, 0))
            self._bytes -= nbytes
            self._counters.pop(source, None)

    def discard_pending(self) -> dict[str, int]:
        """Drop every pending frame (shutdown); returns how many per source, for the caller to count by reason."""
        with self._cond:
            discarded = {source: 1 for source in self._pending}
            self._pending.clear()
            self._bytes = 0
            return discarded

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    @property
    def nbytes(self) -> int:
        with self._cond:
            return self._bytes

    def __len__(self) -> int:
        with self._cond:
            return len(self._pending)

    def counters(self) -> dict[str, QueueCounters]:
        with self._cond:
            return {s: QueueCounters(c.received, c.dropped) for s, c in self._counters.items()}
