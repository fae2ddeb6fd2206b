"""Pairs on their way to the store: the inference path hands them over and never waits (``put`` takes one short
lock); a background thread writes them in batches. While the store cannot be reached or written, pairs wait
here up to ``bound``; beyond it new pairs are counted dropped (those already waiting keep their place, so
every pair accepted during an outage is written when the store returns). A store that was never opened (a
database down at start) is opened by the same thread, retried every ``retry_s``."""

from __future__ import annotations

import logging
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from gcdtrav.schemas.messages import StoreStatus
from gcdtrav.service.store.base import Store
from gcdtrav.service.store.records import PairRecord, PairTotals, StoreError, StoreUnavailable

log = logging.getLogger("gcdtrav.service")
BATCH_PAIRS = 2_000  # pairs per transaction: a drive's burst in one commit, yet a short one
WRITE_EVERY_S = 0.5  # pairs wait at most about this long before their batch is written
TOTALS_EVERY_S = 1.0  # the store's totals (every instance's pairs) are read this often for status and metrics


@dataclass(frozen=True)
class OutboxState:
    """The store as this instance sees it, for status and metrics."""

    backend: str
    location: str
    reachable: bool
    unreachable_since: float | None  # s since the epoch; None while reachable
    error: str | None  # the last failure, one line
    pending: int  # pairs waiting in memory
    written: int  # pairs this instance wrote
    dropped: int  # pairs refused because the outbox was full
    evicted: int  # the store's oldest pairs deleted by this instance's appends (the bounds)


class PairOutbox:
    def __init__(
        self,
        opener: Callable[[], Store],
        backend: str,
        location: str,
        bound: int,
        max_pairs: int,
        max_bytes: int,
        retry_s: float = 2.0,
        clock: Callable[[], float] = time.time,
        max_age_s: float | None = None,
        sample_size: int = 0,
    ) -> None:
        """``opener`` opens the store (it may raise StoreUnavailable: retried); ``backend`` and ``location``
        name it before it is open; ``max_pairs``, ``max_bytes`` and ``max_age_s`` bound the raw pairs."""
        self._opener, self.backend, self.location = opener, backend, location
        self.bound, self.max_pairs, self.max_bytes, self.retry_s, self.clock = (
            bound, max_pairs, max_bytes, retry_s, clock
        )  # fmt: skip
        self.max_age_s, self.sample_size = max_age_s, sample_size
        self._pending: deque[PairRecord] = deque()
        self._changed = threading.Condition()
        self._store: Store | None = None
        self._unreachable_since: float | None = None
        self._error: str | None = None
        self._written = self._dropped = self._evicted = 0
        self._totals = PairTotals(0, 0)  # the whole store's, read by the writer: status never waits on the store
        self._totals_at = -float("inf")
        self._writing = 0  # pairs taken from the queue into the transaction under way
        # a batch whose transaction failed, with its id: written again as it was, before any other (its commit
        # may have happened and only the answer been lost: the store then stores nothing twice)
        self._retry: tuple[str, list[PairRecord]] | None = None
        self._stopping = False
        self._thread = threading.Thread(target=self._write_forever, name="gcdtrav-store", daemon=True)

    # ---- the inference side ----------------------------------------------------------------------------
    def put(self, pairs: Sequence[PairRecord]) -> int:
        """Queue pairs for the store without waiting; the number accepted (the rest counted dropped)."""
        with self._changed:
            room = max(0, self.bound - self._held())
            accepted = list(pairs[:room])
            self._pending.extend(accepted)
            self._dropped += len(pairs) - len(accepted)
            if len(self._pending) >= BATCH_PAIRS:
                self._changed.notify()  # a full batch goes at once; smaller ones wait for WRITE_EVERY_S
        return len(accepted)

    # ---- lifetime --------------------------------------------------------------------------------------
    def open_now(self) -> Store | None:
        """Try to open the store at once (at start); None if it cannot be reached yet (the writer retries).
        Any other StoreError (a newer schema) is raised: the instance refuses it."""
        try:
            self._opened(self._opener())
        except StoreUnavailable as err:
            self._failed(err)
        return self._store

    def start(self) -> None:
        self._thread.start()

    def close(self, timeout_s: float = 5.0) -> None:
        """Write what is waiting (for up to ``timeout_s``), stop the writer, close the store."""
        self.flush(timeout_s)
        with self._changed:
            self._stopping = True
            self._changed.notify_all()
        if self._thread.is_alive():
            self._thread.join(timeout=timeout_s)
        left = self.pending
        if left:
            log.error("store %s: %d pairs not written at shutdown (it was unreachable)", self.location, left)
        if self._store is not None:
            self._store.close()

    def flush(self, timeout_s: float) -> bool:
        """Wait until every queued pair is written; False if the store did not take them within ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        with self._changed:
            self._changed.notify_all()
            while self._held():
                left = deadline - time.monotonic()
                if left <= 0 or not self._thread.is_alive():
                    return False
                self._changed.wait(min(left, 0.05))
        return True

    # ---- what it knows ---------------------------------------------------------------------------------
    @property
    def store(self) -> Store | None:
        """The open store (reads go straight to it), or None while it was never reached."""
        return self._store

    @property
    def totals(self) -> PairTotals:
        """The whole store's pairs and bytes as last read (at most about TOTALS_EVERY_S old while reachable)."""
        with self._changed:
            return self._totals

    @property
    def pending(self) -> int:
        with self._changed:
            return self._held()

    def state(self) -> OutboxState:
        with self._changed:
            return OutboxState(
                backend=self.backend,
                location=self.location,
                reachable=self._unreachable_since is None and self._store is not None,
                unreachable_since=self._unreachable_since,
                error=self._error,
                pending=self._held(),
                written=self._written,
                dropped=self._dropped,
                evicted=self._evicted,
            )

    # ---- the writer ------------------------------------------------------------------------------------
    def _write_forever(self) -> None:
        while True:
            with self._changed:
                if self._stopping:
                    return
                if not (self._pending or self._retry) or self._unreachable_since is not None:
                    self._changed.wait(self.retry_s if self._unreachable_since is not None else WRITE_EVERY_S)
                if self._stopping:
                    return
                if self._retry is not None:
                    batch_id, batch = self._retry
                    self._retry = None
                else:
                    batch_id = uuid.uuid4().hex
                    batch = [self._pending.popleft() for _ in range(min(BATCH_PAIRS, len(self._pending)))]
                self._writing = len(batch)
            self._write(batch_id, batch)

    def _write(self, batch_id: str, batch: list[PairRecord]) -> None:
        try:
            store = self._store or self._opened(self._opener())
            result = (
                store.append_pairs(batch, self.max_pairs, self.max_bytes, batch_id, self.max_age_s, self.sample_size)
                if batch
                else None
            )
        except StoreUnavailable as err:
            self._failed(err)
            with self._changed:
                self._retry = (batch_id, batch) if batch else None  # again first, whole, under its id
                self._writing = 0
                self._changed.notify_all()
            return
        except Exception as err:  # not transient (a refused row, a bug): counted, never retried forever
            log.error("store %s refused %d pairs: %s", self.location, len(batch), err, exc_info=True)
            with self._changed:
                self._dropped += len(batch)
                self._writing = 0
                self._changed.notify_all()
            return
        totals = self._read_totals(store, force=bool(batch))
        with self._changed:
            if result is not None:
                self._written += len(batch) if result.replayed else result.stored  # a replay: written before
                self._evicted += result.evicted
            if totals is not None:
                self._totals, self._totals_at = totals, time.monotonic()
            self._writing = 0
            if self._unreachable_since is not None:
                log.info("store %s reachable again; %d pairs waiting", self.location, len(self._pending))
            self._unreachable_since, self._error = None, None
            self._changed.notify_all()

    def _held(self) -> int:
        """Pairs not yet in the store: queued, in the transaction under way, or waiting to be retried (lock held)."""
        return len(self._pending) + self._writing + (len(self._retry[1]) if self._retry is not None else 0)

    def _read_totals(self, store: Store, force: bool) -> PairTotals | None:
        """The store's totals, after a write or when the last read is older than TOTALS_EVERY_S; None if not
        read (a failure here changes nothing: the pairs are written, the next write reads again)."""
        if not force and time.monotonic() - self._totals_at < TOTALS_EVERY_S:
            return None
        try:
            return store.totals()
        except StoreError:
            return None

    def _opened(self, store: Store) -> Store:
        totals = self._read_totals(store, force=True)
        with self._changed:
            self._store = store
            if totals is not None:
                self._totals, self._totals_at = totals, time.monotonic()
        return store

    def _failed(self, err: StoreError) -> None:
        with self._changed:
            first = self._unreachable_since is None
            if first:
                self._unreachable_since = self.clock()
            self._error = str(err)
        if first:
            log.error("store unreachable: %s; pairs wait in memory (up to %d)", err, self.bound)


def store_status(state: OutboxState) -> StoreStatus:
    """The status message's view of the store."""
    return StoreStatus(
        backend=state.backend,
        location=state.location,
        reachable=state.reachable,
        unreachable_since=state.unreachable_since,
        error=state.error,
        pending_pairs=state.pending,
        written_pairs=state.written,
        dropped_pairs=state.dropped,
    )
