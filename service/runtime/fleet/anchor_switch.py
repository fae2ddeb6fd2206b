"""Hot-swapping the anchor set: validate, prepare, persist, activate, one swap at a time. No middleware here.

A swap recomputes the text embeddings and fsyncs two files, which takes longer than a zenoh callback
should wait, so swaps run on this module's own worker thread and report to a callback; frames keep flowing
meanwhile and each frame uses exactly one set (``Pipeline.activate`` replaces one reference).

Two files, each written atomically (a failed write leaves the old file whole): the history (the last
``HISTORY_LENGTH`` accepted sets with the time each became active, newest first, for ``gcdtrav anchors
history`` and ``rollback``), then the state file, the commit point: the set a restart serves, written before
the set is activated or the swap acknowledged. A crash between the two leaves a history whose head was never
active; the next start puts the active set back at its head, so the two agree. A failed state write refuses
the swap and takes the new entry back out of the history: a refused set never becomes active.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

from gcdtrav.schemas.anchors import AnchorSet, AnchorSetError
from gcdtrav.schemas.messages import AnchorHistoryEntry, AnchorHistoryReply, MessageError
from gcdtrav.service.pipeline import Pipeline
from gcdtrav.service.runtime.fleet.state import (
    remove_stale_temporaries,
    save_anchor_state,
    write_atomically,
)
from gcdtrav.service.store.legacy import history_file_of

log = logging.getLogger("gcdtrav.service")

HISTORY_LENGTH = 20
SwapDone = Callable[[AnchorSet | None, BaseException | None], None]


class AnchorSwitch:
    def __init__(self, pipeline: Pipeline, state_file: Path, instance: str, max_body_bytes: int) -> None:
        self.pipeline = pipeline
        self.state_file = state_file
        self.history_file = history_file_of(state_file)
        self.instance = instance
        self.max_body_bytes = max_body_bytes
        self._lock = threading.Lock()
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="gcdtrav-anchors")
        self._listeners: list[Callable[[AnchorHistoryEntry], None]] = []
        self._history = load_history(self.history_file)
        if not self._history or self._history[0].version != pipeline.anchors.version:
            # The set it started with (rollback can return to it), never accepted in the fleet: accepted_at 0
            # makes it lose to any accepted set another instance announces (service/runtime/fleet/fleet_anchors.py).
            try:
                self._remember(pipeline.anchors, accepted_at=0.0)
            except OSError as err:  # a full or read-only state dir: serve anyway, say so once
                start = AnchorHistoryEntry(
                    accepted_at=0.0, version=pipeline.anchors.version, anchor_set=pipeline.anchors
                )
                self._history = [start, *self._history][:HISTORY_LENGTH]
                log.error(
                    "cannot write the anchor history %s (%s): serving anchor set %s; swaps will fail until the state "
                    "dir is writable",
                    self.history_file,
                    err.strerror or err,
                    pipeline.anchors.version,
                )

    # ---- swaps, on the worker ------------------------------------------------------------------------
    def submit(self, body: bytes, done: SwapDone) -> None:
        """Swap to the anchor set in ``body`` (JSON or YAML) on the worker; ``done(set, error)`` reports."""
        self._run(lambda: self.swap(self.parse(body)), done)

    def submit_rollback(self, steps: int, done: SwapDone) -> None:
        """Swap back to the set ``steps`` entries before the active one, on the worker."""
        self._run(lambda: self.swap(self.rollback_target(steps)), done)

    def submit_adopt(self, fetch: Callable[[], AnchorHistoryEntry | None], done: SwapDone) -> None:
        """Adopt the fleet's set that ``fetch`` returns (it may query the bus: it runs on the worker), keeping
        its accepted_at; nothing if it returns None or the set is already active."""

        def adopt() -> AnchorSet:
            entry = fetch()
            if entry is None:
                raise AnchorSetError(["the fleet's newest set could not be fetched"])
            active = self.head()
            if entry.version == active.version:
                return active.anchor_set
            return self.swap(entry.anchor_set, entry.accepted_at)

        self._run(adopt, done)

    def on_change(self, listener: Callable[[AnchorHistoryEntry], None]) -> None:
        """Call ``listener`` with the new head of the history after every swap (on the worker)."""
        self._listeners.append(listener)

    def head(self) -> AnchorHistoryEntry:
        """The active set's entry (the set, its version, when the fleet accepted it): the one owner of which
        set is active. The pipeline holds the same set with its embeddings, installed by ``swap``, for frames."""
        with self._lock:
            return self._history[0]

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

    def swap(self, anchors: AnchorSet, accepted_at: float | None = None) -> AnchorSet:
        """prepare -> persist -> activate under one lock; the active set stays if any step fails. ``accepted_at``:
        when the fleet accepted it (an adopted set keeps its time), else now."""
        with self._lock:
            prepared = self.pipeline.prepare(anchors)
            before = self._history
            self._remember(anchors, accepted_at)
            try:
                save_anchor_state(self.state_file, anchors)  # the commit point
            except Exception:
                self._restore(before)
                raise
            self.pipeline.activate(prepared)
            head = self._history[0]
        log.info("anchor set swapped to %s (%d anchors)", anchors.version, len(anchors))
        for listener in self._listeners:
            listener(head)
        return anchors

    # ---- history -------------------------------------------------------------------------------------
    def history(self) -> AnchorHistoryReply:
        with self._lock:
            return AnchorHistoryReply(instance=self.instance, entries=list(self._history))

    def rollback_target(self, steps: int) -> AnchorSet:
        with self._lock:
            if not 1 <= steps < len(self._history):
                raise AnchorSetError(
                    [f"no set {steps} step(s) back: the history holds {len(self._history)} set(s), the active first"]
                )
            return self._history[steps].anchor_set

    def _remember(self, anchors: AnchorSet, accepted_at: float | None = None) -> None:
        when = round(time.time(), 3) if accepted_at is None else accepted_at  # ms: the fleet's tokens carry ms
        entry = AnchorHistoryEntry(accepted_at=when, version=anchors.version, anchor_set=anchors)
        self._write_history([entry, *self._history][:HISTORY_LENGTH])

    def _restore(self, entries: list[AnchorHistoryEntry]) -> None:
        """Take a refused swap's entry back out (best effort: the next start puts the active set at the head)."""
        try:
            self._write_history(entries)
        except OSError as err:
            self._history = entries
            log.warning("could not take the refused set out of %s: %s", self.history_file, err)

    def _write_history(self, entries: list[AnchorHistoryEntry]) -> None:
        reply = AnchorHistoryReply(instance=self.instance, entries=entries)
        write_atomically(self.history_file, reply.model_dump_json(indent=1) + "\n")
        self._history = entries  # only once written: a failed write leaves the history as it was

    def close(self) -> None:
        self._worker.shutdown(wait=True)


def load_history(history_file: Path) -> list[AnchorHistoryEntry]:
    """The accepted sets, newest (the active one) first; empty if there is no usable history file."""
    try:
        if history_file.parent.is_dir():
            remove_stale_temporaries(history_file)  # writes a crash interrupted
        if not history_file.is_file():
            return []
        return AnchorHistoryReply.model_validate_json(history_file.read_text("utf-8")).entries
    except (OSError, ValueError, MessageError) as err:
        log.error("ignoring the anchor history file %s: %s", history_file, err)
        return []
