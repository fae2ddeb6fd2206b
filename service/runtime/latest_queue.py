"""Latest-only frame queue: one pending frame per source (two with the glance), served by a policy.

A robot publishes faster than a CPU infers. Keeping only the newest unprocessed frame per source bounds
memory (sources x one payload) whatever the input rate, and serving sources in turn keeps one fast
robot from starving the others.

Which waiting source goes next is the ``policy``'s (service/runtime/share.py): round-robin (the source
waiting longest), or a weighted share by need. It reads each ready frame's claim: its class (first, urgent,
news, refresh) and its source's need. With ``triage`` on, a frame first arrives in the source's *arrival*
slot, is glanced at (``take_untriaged``) and settled: reused (it leaves the queue, never inferred) or moved
to the source's *ready* slot with the glance's claim, replacing an older ready frame. A source then holds at
most two frames: the newest arrival and the newest ready one. Without triage a frame is ready at once, as
news. Two claims are the queue's own: a source's first frame (nothing received from it before) is *first*
until anything more comes from it, and an *urgent* wait stays urgent until the source's turn, whatever
frame replaces the one that made it so (its consumers still hold maps of a view that is gone).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Generic, TypeVar

from gcdtrav.service.runtime.share import NEWS_CLAIM, Claim, FrameClass, RoundRobin, SharePolicy, Waiting

T = TypeVar("T")


@dataclass
class QueueCounters:
    received: int = 0
    dropped: int = 0  # replaced by a newer frame before it was taken


class PendingBudgetExceeded(Exception):
    """The frame would take the pending frames of all sources over the queue's byte budget."""


@dataclass
class _Entry(Generic[T]):
    item: T
    nbytes: int


@dataclass
class _Slot(Generic[T]):
    arrived: _Entry[T] | None = None  # to be glanced at (triage only)
    glancing: bool = False  # the arrival is being glanced at
    ready: _Entry[T] | None = None  # to be inferred
    since: float = 0.0  # monotonic: when the ready frame began waiting (kept when a newer one replaces it)
    claim: Claim = NEWS_CLAIM  # the ready frame's class and its source's need, for the policy

    @property
    def empty(self) -> bool:
        return self.arrived is None and self.ready is None


@dataclass
class LatestFrameQueue(Generic[T]):
    max_bytes: int | None = None  # all pending frames together; None: one frame per source is the only bound
    policy: SharePolicy = field(default_factory=RoundRobin)
    triage: bool = False  # frames are glanced at (take_untriaged, settle) before they may be inferred
    clock: Callable[[], float] = time.monotonic
    _pending: dict[str, _Slot[T]] = field(default_factory=dict)
    _counters: dict[str, QueueCounters] = field(default_factory=dict)
    _cond: threading.Condition = field(default_factory=threading.Condition)
    _closed: bool = False
    _bytes: int = 0

    def put(self, source: str, item: T, nbytes: int = 0) -> bool:
        """Store ``item`` as the source's newest frame. Returns False if it replaced (dropped) an older one.

        Raises PendingBudgetExceeded, keeping what is queued, if ``nbytes`` more would exceed ``max_bytes``.
        """
        with self._cond:
            counters = self._received(source)
            slot = self._pending.get(source) or _Slot()
            older = slot.arrived if self.triage else slot.ready
            freed = older.nbytes if older is not None else 0
            if self.max_bytes is not None and self._bytes - freed + nbytes > self.max_bytes:
                raise PendingBudgetExceeded(f"{nbytes} bytes would take the pending frames over {self.max_bytes} bytes")
            if older is not None:
                counters.dropped += 1
            entry = _Entry(item, nbytes)
            if self.triage:
                slot.arrived, slot.glancing = entry, False
            else:
                slot.since = slot.since if slot.ready is not None else self.clock()
                slot.ready, slot.claim = entry, self._claim(source, slot, NEWS_CLAIM)
            self._pending[source] = slot
            self._bytes += nbytes - freed
            self._cond.notify_all()
            return older is None

    def count_unqueued(self, source: str) -> None:
        """Count a frame that was received but refused before queueing (e.g. over the byte limit)."""
        with self._cond:
            self._received(source)

    def _received(self, source: str) -> QueueCounters:
        """Count a frame received from ``source``: its first frame waiting is no longer a stranger's."""
        counters = self._counters.setdefault(source, QueueCounters())
        counters.received += 1
        slot = self._pending.get(source)
        if slot is not None and slot.claim.kind is FrameClass.FIRST:
            slot.claim = Claim(FrameClass.NEWS, slot.claim.need)
        return counters

    def _claim(self, source: str, slot: _Slot[T], claim: Claim) -> Claim:
        """The claim of the frame now ready in ``slot``: a source's first frame is first, an urgent wait stays
        urgent until the source's turn, else the glance's."""
        if self._counters[source].received == 1:
            return Claim(FrameClass.FIRST, claim.need)
        if slot.ready is not None and slot.claim.kind is FrameClass.URGENT:
            return Claim(FrameClass.URGENT, claim.need)
        return claim

    def take(self, timeout: float | None = None) -> tuple[str, T] | None:
        """The next source's newest ready frame, by the policy; None on timeout or after close()."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._any_ready() or self._closed, timeout):
                return None
            waiting = [Waiting(source, slot.since, slot.claim) for source, slot in self._pending.items() if slot.ready]
            if not waiting:
                return None
            now = self.clock()
            chosen = self.policy.choose(waiting, now)
            self.policy.taken(chosen, now)
            source = chosen.source
            slot = self._pending[source]
            entry, slot.ready, slot.claim = slot.ready, None, NEWS_CLAIM
            assert entry is not None
            self._bytes -= entry.nbytes
            if slot.empty:
                del self._pending[source]
            return source, entry.item

    def _any_ready(self) -> bool:
        return any(slot.ready is not None for slot in self._pending.values())

    def take_untriaged(self, timeout: float | None = None) -> tuple[str, T] | None:
        """The next arrival to glance at (it stays queued until ``settle``); None on timeout or after close()."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._unglanced() is not None or self._closed, timeout):
                return None
            source = self._unglanced()
            if source is None:
                return None
            slot = self._pending.pop(source)  # to the back: glances go round the sources
            self._pending[source] = slot
            assert slot.arrived is not None
            slot.glancing = True
            return source, slot.arrived.item

    def _unglanced(self) -> str | None:
        return next((s for s, slot in self._pending.items() if slot.arrived is not None and not slot.glancing), None)

    def settle(self, source: str, item: T, claim: Claim | None) -> bool:
        """The glance's verdict on the arrival ``item``: None, reused (it leaves the queue), or ready for
        inference with ``claim`` (replacing an older ready frame, counted dropped). False if ``item`` is no
        longer the source's arrival (replaced by a newer frame, or its source forgotten): nothing changed."""
        with self._cond:
            slot = self._pending.get(source)
            if slot is None or slot.arrived is None or slot.arrived.item is not item:
                return False
            entry, slot.arrived, slot.glancing = slot.arrived, None, False
            if claim is None:
                self._bytes -= entry.nbytes
            else:
                slot.claim = self._claim(source, slot, claim)
                if slot.ready is not None:
                    self._bytes -= slot.ready.nbytes
                    self._counters.setdefault(source, QueueCounters()).dropped += 1
                else:
                    slot.since = self.clock()
                slot.ready = entry
                self._cond.notify_all()
            if slot.empty:
                del self._pending[source]
            return True

    def settle_in_line(self, source: str, item: T) -> T | None:
        """The arrival ``item`` takes the place of the source's ready frame, which keeps its place in line
        (``since``): the frame to answer without inference is returned, the replaced one, or ``item`` itself
        if no frame is ready any more (taken meanwhile). None if ``item`` is no longer the source's arrival."""
        with self._cond:
            slot = self._pending.get(source)
            if slot is None or slot.arrived is None or slot.arrived.item is not item:
                return None
            entry, slot.arrived, slot.glancing = slot.arrived, None, False
            replaced = slot.ready
            if replaced is not None:
                slot.ready = entry
            answered = replaced if replaced is not None else entry
            self._bytes -= answered.nbytes
            if slot.empty:
                del self._pending[source]
            return answered.item

    def has_ready(self, source: str) -> bool:
        """Whether a frame of ``source`` waits for inference."""
        with self._cond:
            slot = self._pending.get(source)
            return slot is not None and slot.ready is not None

    def forget(self, source: str) -> None:
        """Drop the source's pending frames and counters (a source the service no longer tracks)."""
        with self._cond:
            slot = self._pending.pop(source, None)
            if slot is not None:
                self._bytes -= sum(entry.nbytes for entry in (slot.arrived, slot.ready) if entry is not None)
            self._counters.pop(source, None)
        self.policy.forget(source)

    def discard_pending(self) -> dict[str, int]:
        """Drop every pending frame (shutdown); returns how many per source, for the caller to count by reason."""
        with self._cond:
            discarded = {
                source: (slot.arrived is not None) + (slot.ready is not None) for source, slot in self._pending.items()
            }
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
        """Frames waiting: to be glanced at or to be inferred."""
        with self._cond:
            return sum((slot.arrived is not None) + (slot.ready is not None) for slot in self._pending.values())

    def counters(self) -> dict[str, QueueCounters]:
        with self._cond:
            return {s: QueueCounters(c.received, c.dropped) for s, c in self._counters.items()}
