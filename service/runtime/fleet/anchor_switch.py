"""Hot-swapping the anchor set: validate, prepare, record, activate, one swap at a time. No middleware here.

The fleet's store (``service/store``) is the record of which set is active and of every set that was: a swap
is one compare-and-swap transaction there (``Store.activate``), so of two operators swapping at once exactly
one wins and the other learns whose set it lost to. The start set (configured, or an instance's old anchor
state file, imported once) seeds an empty store only; a store holding an active set overrides it, so the set
an operator applied survives any restart, even of every instance on empty state dirs (PostgreSQL). The files
of an instance before the store are imported once when the store opens (``service/store/legacy.py``).

A swap recomputes the text embeddings, which takes longer than a zenoh callback should wait, so swaps run on
this module's own worker thread and report to a callback; frames keep flowing meanwhile and each frame uses
exactly one set (``Pipeline.activate`` replaces one reference). The store is written before the set is
activated here or the swap acknowledged: a refused or lost swap never becomes active.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

from gcdtrav.schemas.anchors import AnchorSet, AnchorSetError
from gcdtrav.schemas.experience import AnchorProposal
from gcdtrav.schemas.messages import AnchorHistoryEntry, AnchorHistoryReply
from gcdtrav.service.pipeline import Pipeline
from gcdtrav.service.runtime.fleet.fleet_anchors import ActiveSet
from gcdtrav.service.store import HistoryRecord, Store, StoreError

T = TypeVar("T")
log = logging.getLogger("gcdtrav.service")

HISTORY_LENGTH = 20
SwapDone = Callable[[AnchorSet | None, BaseException | None], None]


class ActivationLost(AnchorSetError):
    """The compare-and-swap lost: another set became active first; ``winner`` is it. Nothing changed here."""

    def __init__(self, winner: HistoryRecord, expected: str | None) -> None:
        super().__init__(
            [
                f"anchor set {winner.version} was activated first (by {winner.instance or 'another instance'}); "
                f"this request expected {expected} to be active: nothing swapped"
            ]
        )
        self.winner = winner


def entry_of(record: HistoryRecord) -> AnchorHistoryEntry:
    return AnchorHistoryEntry(
        accepted_at=record.accepted_at,
        version=record.version,
        anchor_set=record.anchor_set,
        forced=record.forced,
        activated_by=record.instance or None,
        how=record.how,
    )


class AnchorSwitch:
    def __init__(
        self, pipeline: Pipeline, store: Store | Callable[[], Store], instance: str, max_body_bytes: int
    ) -> None:
        """``store``: the fleet's store, or what returns it once open (StoreUnavailable until then: the start set
        is served meanwhile, and ``sync`` installs the store's active set once it answers)."""
        self.pipeline, self.instance = pipeline, instance
        self._store_of: Callable[[], Store] = (lambda: store) if isinstance(store, Store) else store
        self.max_body_bytes = max_body_bytes
        self._synced = False  # the store's active set was read (or seeded) once
        self._lock = threading.Lock()
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="gcdtrav-anchors")
        # the store's reads for queries (history, calibration, a proposal's fit and keeping): off zenoh's callback
        # threads, and never holding up a swap on the worker
        self._reader = ThreadPoolExecutor(max_workers=1, thread_name_prefix="gcdtrav-anchor-reads")
        self._listeners: list[Callable[[AnchorHistoryEntry], None]] = []
        start = pipeline.anchors
        self._head = AnchorHistoryEntry(accepted_at=0.0, version=start.version, anchor_set=start)
        self._history = [self._head]  # the last history read from the store, for when it is unreachable
        try:
            self._install(self.store.seed(start, instance))  # the start set seeds an empty store only
            self._synced = True
        except StoreError as err:  # serve the start set; swaps say the store is unreachable
            log.error("anchor store: %s; serving anchor set %s until it answers", err, start.version)

    @property
    def store(self) -> Store:
        """The fleet's store; StoreUnavailable while it was never reached."""
        return self._store_of()

    def sync(self, done: SwapDone) -> bool:
        """Once the store answers after a start without it: install its active set (seeding an empty store
        with the set served), on the worker. False (nothing to do) once that happened or while it is away."""
        if self._synced:
            return False
        try:
            store = self.store
        except StoreError:
            return False
        self._synced = True

        def install() -> AnchorSet:
            with self._lock:
                served = self._head
                try:
                    self._install(store.seed(self.pipeline.anchors, self.instance))
                except StoreError:
                    self._synced = False  # away again: the next call tries again
                    raise
                head = self._head
            if head != served:
                self._tell(head)
            return head.anchor_set

        self._run(install, done)
        return True

    # ---- swaps, on the worker ------------------------------------------------------------------------
    def submit(
        self, body: bytes, done: SwapDone, expected: str | None = None, how: str = "set", forced: bool = False
    ) -> None:
        """Swap to the anchor set in ``body`` (JSON or YAML) on the worker if ``expected`` (None: whichever) is
        the active version; ``done(set, error)`` reports."""
        self._run(lambda: self.swap(self.parse(body), expected, how, forced), done)

    def submit_proposal(self, version: str, expected: str | None, force: bool, done: SwapDone) -> None:
        """Apply the kept proposal ``version`` on the worker: its proposed set, exactly as the operator reviewed it
        (never refitted), compared against the set it was judged against unless ``expected`` names another;
        refused if gone, or if not judged better without ``force`` (then marked forced in the history)."""

        def apply() -> AnchorSet:
            try:
                kept = self.store.proposal(version)
            except StoreError as err:
                raise AnchorSetError([f"the anchor store is unreachable ({err}): nothing applied"]) from None
            if kept is None:
                gone = f"no kept proposal {version}: it is gone (pruned, or never made); gcdtrav anchors propose"
                raise AnchorSetError([gone])
            verdict = kept.proposal.judged()
            if not verdict.applicable and not force:
                refused = f"proposal {version} is not applied: {verdict.reason()}; force=true applies it"
                raise AnchorSetError([refused])
            expected_version = expected or kept.proposal.current_version
            return self.swap(kept.proposal.proposed, expected_version, "proposal", forced=not verdict.applicable)

        self._run(apply, done)

    def read_later(self, job: Callable[[], T], done: Callable[[T | None, BaseException | None], None]) -> None:
        """``job`` (a read of the store, a proposal's fit) on the switch's reader, then ``done(result, error)``."""

        def report(future: Future[T]) -> None:
            error = future.exception()
            done(None if error is not None else future.result(), error)

        self._reader.submit(job).add_done_callback(report)

    def keep_proposal(self, proposal: AnchorProposal) -> AnchorProposal:
        """The proposal kept in the store, so that what the operator reviews is what `anchors apply` applies;
        unkept (said so in the reply) when the store does not answer."""
        kept = proposal.model_copy(update={"kept": True})
        try:
            self.store.put_proposal(kept, self.instance)
        except StoreError as err:
            log.error("proposal %s not kept: the store does not answer (%s)", proposal.proposed_version, err)
            return proposal
        return kept

    def submit_rollback(self, steps: int, done: SwapDone, expected: str | None = None) -> None:
        """Swap back to the set ``steps`` entries before the active one of the store's history, on the worker."""

        def roll_back() -> AnchorSet:
            target, active = self.rollback_target(steps)
            return self.swap(target, expected or active, "rollback")

        self._run(roll_back, done)

    def submit_adopt(
        self, announced: ActiveSet, fetch: Callable[[], AnchorHistoryEntry | None], done: SwapDone
    ) -> None:
        """Serve the set another instance announced. The store is the record: when it holds that set, or a newer
        one, that is installed here; only an instance with a store of its own (no shared PostgreSQL) fetches
        the set with ``fetch`` (it may query the bus: it runs on the worker) and records it, keeping its time."""
        self._run(lambda: self._adopt(announced, fetch), done)

    def _adopt(self, announced: ActiveSet, fetch: Callable[[], AnchorHistoryEntry | None]) -> AnchorSet:
        with self._lock:
            try:
                recorded = self.store.active()
            except StoreError:  # away: the announcer's set, fetched over the bus, cannot be recorded either
                recorded = None
            served, installed = self._head, None
            if recorded is not None and ActiveSet.of(recorded.accepted_at, recorded.version) >= announced:
                self._install(recorded)
                installed = self._head
        if installed is not None:
            if installed != served:
                self._tell(installed)
            return installed.anchor_set
        entry = fetch()
        if entry is None:
            raise AnchorSetError(["the fleet's newest set could not be fetched"])
        return self.swap(entry.anchor_set, None, entry.how or "set", entry.forced, accepted_at=entry.accepted_at)

    def on_change(self, listener: Callable[[AnchorHistoryEntry], None]) -> None:
        """Call ``listener`` with the new active entry after every swap (on the worker)."""
        self._listeners.append(listener)

    def head(self) -> AnchorHistoryEntry:
        """The entry of the set this instance serves (the set, its version, when the fleet accepted it). The
        pipeline holds the same set with its embeddings, installed by ``swap``, for frames. Read without the
        lock: the frame's triage asks it (reuse compares versions), and a swap holds the lock while it waits on
        the store (issue 46: the inference path never waits on the store); the entry is replaced whole."""
        return self._head

    def _run(self, job: Callable[[], AnchorSet], done: SwapDone) -> None:
        def report(future: Future[AnchorSet]) -> None:
            error = future.exception()
            done(None if error is not None else future.result(), error)

        self._worker.submit(job).add_done_callback(report)

    def parse(self, body: bytes) -> AnchorSet:
        if len(body) > self.max_body_bytes:
            raise AnchorSetError(
                [
                    f"body of {len(body)} bytes is over the limit of {self.max_body_bytes} bytes "
                    "(max_anchor_set_bytes); an anchor set of 64 anchors takes about 4 kB"
                ]
            )
        return AnchorSet.from_text(body, source="anchor set")

    def swap(
        self,
        anchors: AnchorSet,
        expected: str | None = None,
        how: str = "set",
        forced: bool = False,
        accepted_at: float | None = None,
    ) -> AnchorSet:
        """prepare -> record (compare-and-swap on ``expected``; None: whichever is active) -> activate, under one
        lock; the active set stays if any step fails, ActivationLost if another set won. The set already
        active in the store is only installed here (every instance receives an operator's swap)."""
        with self._lock:
            prepared = self.pipeline.prepare(anchors)
            recorded = self._record(anchors, expected, how, forced, accepted_at)
            self.pipeline.activate(prepared)
            self._head = entry_of(recorded)
            head = self._head
        log.info("anchor set swapped to %s (%d anchors, %s)", anchors.version, len(anchors), how)
        self._tell(head)
        return anchors

    def _record(
        self, anchors: AnchorSet, expected: str | None, how: str, forced: bool, accepted_at: float | None
    ) -> HistoryRecord:
        try:
            active = self.store.active()
            if active is not None and active.version == anchors.version:
                return active  # already the record's: another instance took the same request first
            activation = self.store.activate(
                anchors, expected, how, self.instance, forced=forced, accepted_at=accepted_at
            )
        except StoreError as err:
            raise AnchorSetError([f"the anchor store is unreachable ({err}): nothing swapped"]) from None
        if not activation.applied and activation.active.version != anchors.version:
            raise ActivationLost(activation.active, expected)
        return activation.active

    def _install(self, record: HistoryRecord) -> None:
        """Serve the record's set here (embeddings computed when it is not the one served already)."""
        if record.version != self.pipeline.anchors.version:
            self.pipeline.activate(self.pipeline.prepare(record.anchor_set))
            log.info("anchor set %s from the store (%s by %s)", record.version, record.how, record.instance or "-")
        self._head = entry_of(record)

    def _tell(self, head: AnchorHistoryEntry) -> None:
        for listener in self._listeners:
            listener(head)

    # ---- history -------------------------------------------------------------------------------------
    def history(self) -> AnchorHistoryReply:
        """The store's history, newest (active) first; the last one read when the store does not answer."""
        try:
            entries = [entry_of(record) for record in self.store.history(HISTORY_LENGTH)]
        except StoreError as err:
            log.warning("anchor history from memory: the store does not answer (%s)", err)
            with self._lock:
                entries = list(self._history)
        else:
            with self._lock:
                self._history = entries or [self._head]
        return AnchorHistoryReply(instance=self.instance, entries=entries or [self.head()])

    def rollback_target(self, steps: int) -> tuple[AnchorSet, str]:
        """The set ``steps`` activations before the active one in the store, and the active version."""
        try:
            entries = self.store.history(HISTORY_LENGTH)
        except StoreError as err:
            raise AnchorSetError([f"the anchor store is unreachable ({err}): nothing rolled back"]) from None
        if not 1 <= steps < len(entries):
            raise AnchorSetError(
                [f"no set {steps} step(s) back: the history holds {len(entries)} set(s), the active first"]
            )
        return entries[steps].anchor_set, entries[0].version

    def close(self) -> None:
        self._reader.shutdown(wait=True)
        self._worker.shutdown(wait=True)
