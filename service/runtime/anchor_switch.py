"""Hot-swapping the anchor set: validate, prepare, persist, activate, one swap at a time. No middleware here.

A swap recomputes the text embeddings and fsyncs two files, which takes longer than a zenoh callback
should wait, so swaps run on this module's own worker thread and report to a callback; frames keep flowing
meanwhile and each frame uses exactly one set (``Pipeline.activate`` replaces one reference).

The history file (the last ``HISTORY_LENGTH`` accepted sets with the time each became active, newest first,
for ``gcdtrav anchors history`` and ``rollback``) is the one commit point: written atomically before the set
is activated or the swap acknowledged, and its head is the set a restart serves. The state file, the active
set alone as versions before 1.1 read it, is a mirror written after it; a crash or a failed write between
the two leaves the mirror behind, and the next start repairs it. A swap whose history write fails is
refused and changes nothing (the atomic write leaves the old file whole).
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
from gcdtrav.service.runtime.state import (
    load_anchor_state,
    remove_stale_temporaries,
    save_anchor_state,
    write_atomically,
)

log = logging.getLogger("gcdtrav.service")

HISTORY_LENGTH = 20
SwapDone = Callable[[AnchorSet | None, BaseException | None], None]


def history_file_of(state_file: Path) -> Path:
    return state_file.with_name(state_file.name.removesuffix(".json") + "-history.json")


class AnchorSwitch:
    def __init__(self, pipeline: Pipeline, state_file: Path, instance: str, max_body_bytes: int) -> None:
        self.pipeline = pipeline
        self.state_file = state_file
        self.history_file = history_file_of(state_file)
        self.instance = instance
        self.max_body_bytes = max_body_bytes
        self._lock = threading.Lock()
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="gcdtrav-anchors")
        self._history = load_history(self.history_file)
        if not self._history or self._history[0].version != pipeline.anchors.version:
            self._remember(pipeline.anchors)  # the set it started with: rollback can return to it
        self._mirror(pipeline.anchors)  # repairs a mirror a crash left behind the history

    # ---- swaps, on the worker ------------------------------------------------------------------------
    def submit(self, body: bytes, done: SwapDone) -> None:
        """Swap to the anchor set in ``body`` (JSON or YAML) on the worker; ``done(set, error)`` reports."""
        self._run(lambda: self.swap(self.parse(body)), done)

    def submit_rollback(self, steps: int, done: SwapDone) -> None:
        """Swap back to the set ``steps`` entries before the active one, on the worker."""
        self._run(lambda: self.swap(self.rollback_target(steps)), done)

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

    def swap(self, anchors: AnchorSet) -> AnchorSet:
        """prepare -> persist -> activate under one lock; the active set stays if any step fails."""
        with self._lock:
            prepared = self.pipeline.prepare(anchors)
            self._remember(anchors)  # the commit point
            self._mirror(anchors)
            self.pipeline.activate(prepared)
        log.info("anchor set swapped to %s (%d anchors)", anchors.version, len(anchors))
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

    def _remember(self, anchors: AnchorSet) -> None:
        entry = AnchorHistoryEntry(accepted_at=time.time(), version=anchors.version, anchor_set=anchors)
        entries = [entry, *self._history][:HISTORY_LENGTH]
        reply = AnchorHistoryReply(instance=self.instance, entries=entries)
        write_atomically(self.history_file, reply.model_dump_json(indent=1) + "\n")
        self._history = entries  # only once written: a failed write leaves the history as it was

    def _mirror(self, anchors: AnchorSet) -> None:
        """The state file for readers before 1.1; behind the history after a crash, repaired at the next start."""
        if load_anchor_state(self.state_file) == anchors:
            return
        try:
            save_anchor_state(self.state_file, anchors)
        except OSError as err:
            log.warning("could not mirror the active anchor set to %s: %s", self.state_file, err)

    def close(self) -> None:
        self._worker.shutdown(wait=True)


def load_history(history_file: Path) -> list[AnchorHistoryEntry]:
    """The accepted sets, newest (the active one) first; empty if there is no usable history file."""
    if history_file.parent.is_dir():
        remove_stale_temporaries(history_file)  # writes a crash interrupted
    if not history_file.is_file():
        return []
    try:
        return AnchorHistoryReply.model_validate_json(history_file.read_text("utf-8")).entries
    except (OSError, ValueError, MessageError) as err:
        log.error("ignoring the anchor history file %s: %s", history_file, err)
        return []


def persisted_anchor_set(state_file: Path) -> AnchorSet | None:
    """The set a restart serves: the history's head (the commit point), else the state file (written by
    versions before 1.1, which kept no history or wrote the state first)."""
    history = load_history(history_file_of(state_file))
    return history[0].anchor_set if history else load_anchor_state(state_file)
