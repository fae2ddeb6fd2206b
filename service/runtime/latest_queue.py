"""Latest-only, round-robin frame queue: one pending slot per source.

A robot publishes faster than a CPU infers. Keeping only the newest unprocessed frame per source bounds
memory (sources x one payload) whatever the input rate, and serving sources in turn keeps one fast
robot from starving the others.

Sources whose first frame is waiting take at most every other turn while a returning source waits: a
flood of new names (a frame counter in the key, a hostile peer) then gets at most half of the inference,
and the robots that keep streaming the other half, instead of one turn in (flood + robots).

Which waiting source goes next is the ``policy``'s (service/runtime/share.py): round-robin by default, or
a weighted share by need. With ``triage`` on, a frame is first glanced at (``take_untriaged``) and then
either settled as reused (it leaves the queue, never inferred) or ready for inference; a source's newer
frame replacing a ready one stays ready, so a source never loses its turn to the glance.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Generic, TypeVar

from gcdtrav.service.runtime.share import RoundRobin, SharePolicy, Waiting

T = TypeVar("T")


@dataclass
class QueueCounters:
    received: int = 0
    dropped: int = 0  # replaced by a newer frame before it was taken


class PendingBudgetExceeded(Exception):
    """The frame would take the pending frames of all sources over the queue's byte budget."""


@dataclass
class _Slot(Generic[T]):
    item: T
    nbytes: int
    since: float  # monotonic: when the source began waiting (kept when a newer frame replaces the item)
    ready: bool  # may be taken for inference
    glanced: bool  # the triage has this item (or needs none)


@dataclass
class LatestFrameQueue(Generic[T]):
    max_bytes: int | None = None  # all pending frames together; None: one frame per source is the only bound
    policy: SharePolicy = field(default_factory=RoundRobin)
    triage: bool = False  # frames are glanced at (take_untriaged, settle) before they may be inferred
    clock: Callable[[], float] = time.monotonic
    _pending: OrderedDict[str, _Slot[T]] = field(default_factory=OrderedDict)
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
            freed = older.nbytes if older is not None else 0
            if self.max_bytes is not None and self._bytes - freed + nbytes > self.max_bytes:
                raise PendingBudgetExceeded(f"{nbytes} bytes would take the pending frames over {self.max_bytes} bytes")
            if older is not None:
                counters.dropped += 1
            # A replaced item keeps the source's place in the rotation; a new one joins at the back.
            since = older.since if older is not None else self.clock()
            ready = not self.triage or (older is not None and older.ready)
            self._pending[source] = _Slot(item, nbytes, since, ready, glanced=not self.triage)
            self._bytes += nbytes - freed
            self._cond.notify_all()
            return older is None

    def count_unqueued(self, source: str) -> None:
        """Count a frame that was received but refused before queueing (e.g. over the byte limit)."""
        with self._cond:
            self._counters.setdefault(source, QueueCounters()).received += 1

    def take(self, timeout: float | None = None) -> tuple[str, T] | None:
        """The next source's newest frame ready for inference, by the policy; None on timeout or after close()."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._any_ready() or self._closed, timeout):
                return None
            waiting = [Waiting(source, slot.since) for source, slot in self._pending.items() if slot.ready]
            if not waiting:
                return None
            if self._last_took_new:  # a new source's first frame takes at most every other turn
                waiting = [w for w in waiting if not self._is_new(w.source)] or waiting
            now = self.clock()
            source = self.policy.choose(waiting, now)
            self.policy.taken(source, now)
            self._last_took_new = self._is_new(source)
            slot = self._pending.pop(source)
            self._bytes -= slot.nbytes
            return source, slot.item

    def _any_ready(self) -> bool:
        return any(slot.ready for slot in self._pending.values())

    def take_untriaged(self, timeout: float | None = None) -> tuple[str, T] | None:
        """A frame not yet glanced at (it stays queued: ``settle`` says what becomes of it); None on timeout or
        after close()."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._unglanced() is not None or self._closed, timeout):
                return None
            source = self._unglanced()
            if source is None:
                return None
            slot = self._pending[source]
            slot.glanced = True
            return source, slot.item

    def _unglanced(self) -> str | None:
        return next((source for source, slot in self._pending.items() if not slot.glanced), None)

    def settle(self, source: str, item: T, reused: bool) -> bool:
        """The glance's verdict on ``item``: reused (it leaves the queue) or ready for inference. False if the
        item is no longer queued (replaced by a newer frame, taken, or its source forgotten): nothing changed."""
        with self._cond:
            slot = self._pending.get(source)
            if slot is None or slot.item is not item:
                return False
            if reused:
                del self._pending[source]
                self._bytes -= slot.nbytes
            else:
                slot.ready = True
                self._cond.notify_all()
            return True

    def _is_new(self, source: str) -> bool:
        """Its first frame: nothing received from it before (forgotten sources start again)."""
        return self._counters[source].received == 1

    def forget(self, source: str) -> None:
        """Drop the source's pending frame and counters (a source the service no longer tracks)."""
        with self._cond:
            slot = self._pending.pop(source, None)
            self._bytes -= slot.nbytes if slot is not None else 0
            self._counters.pop(source, None)
        self.policy.forget(source)

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
