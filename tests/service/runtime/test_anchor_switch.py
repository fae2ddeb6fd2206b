"""AnchorSwitch without a bus, over a real SQLite store: swaps run on its own worker (never the caller's
thread, which in the service is zenoh's callback), each step in order, and a failing step (the embeddings, the
store) leaves the active set and the store's history as they were. The compare-and-swap between instances,
the seed and the restart are in tests/service/store/test_anchor_activation.py, over both backends."""

from __future__ import annotations

import threading
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest
from gcdtrav.schemas.anchors import AnchorSet, AnchorSetError, default_anchor_set
from gcdtrav.schemas.config import EngineSettings
from gcdtrav.service.backends.base import BackendDescription
from gcdtrav.service.pipeline import Pipeline
from gcdtrav.service.runtime.fleet.anchor_switch import AnchorSwitch
from gcdtrav.service.store import StoreUnavailable
from gcdtrav.service.store.sqlite import SqliteStore
from numpy.typing import NDArray

TWO = AnchorSet.model_validate(
    {"anchors": [{"concept": "water", "position": 0.02, "width": 0.05}, {"concept": "asphalt", "position": 0.98}]}
)


class ThreadRecordingBackend:
    """Records which thread prepared which concepts; ``fail_on`` makes prepare raise for that concept."""

    model_id = "thread-recording"

    def __init__(self) -> None:
        self.prepared_on: list[tuple[str, tuple[str, ...]]] = []
        self.fail_on: str | None = None

    def describe(self) -> BackendDescription:
        return BackendDescription(self.model_id)

    def prepare(self, concepts: Sequence[str]) -> object:
        if self.fail_on in concepts:
            raise RuntimeError(f"cannot embed '{self.fail_on}'")
        self.prepared_on.append((threading.current_thread().name, tuple(concepts)))
        return tuple(concepts)

    def logits(self, image_rgb: NDArray[np.uint8], prepared: object) -> NDArray[np.float32]:
        return np.zeros((len(prepared), 2, 2), np.float32)  # type: ignore[arg-type]


def swap_and_wait(submit: object, *args: object) -> tuple[AnchorSet | None, BaseException | None, str]:
    """Submit, wait for the report; returns (set, error, name of the thread the report came from)."""
    reported = threading.Event()
    result: list[object] = []

    def done(anchors: AnchorSet | None, error: BaseException | None) -> None:
        result.extend([anchors, error, threading.current_thread().name])
        reported.set()

    submit(*args, done)  # type: ignore[operator]
    assert reported.wait(60), "the swap never reported"
    return result[0], result[1], result[2]  # type: ignore[return-value]


@pytest.fixture
def switch(tmp_path: Path):  # type: ignore[no-untyped-def]
    backend = ThreadRecordingBackend()
    pipeline = Pipeline(backend, default_anchor_set(), EngineSettings())
    store = SqliteStore(tmp_path / "store.sqlite3")
    switch = AnchorSwitch(pipeline, store, "test", max_body_bytes=65536)
    yield switch, pipeline, backend
    switch.close()
    store.close()


def test_a_swap_runs_on_the_worker_and_is_recorded_before_it_activates(switch) -> None:  # type: ignore[no-untyped-def]
    switch, pipeline, backend = switch
    anchors, error, reporter = swap_and_wait(switch.submit, TWO.model_dump_json().encode())
    assert error is None and anchors is not None and anchors.version == TWO.version
    caller = threading.current_thread().name
    assert backend.prepared_on[-1] == (reporter, ("water", "asphalt"))  # prepared where it reported
    assert reporter.startswith("gcdtrav-anchors") and reporter != caller
    assert pipeline.anchors.version == TWO.version
    active = switch.store.active()
    assert active is not None and active.version == TWO.version and active.how == "set" and active.instance == "test"
    assert [entry.version for entry in switch.history().entries] == [TWO.version, default_anchor_set().version]
    assert [entry.how for entry in switch.history().entries] == ["set", "seeded"]


def test_a_failed_swap_changes_nothing(switch) -> None:  # type: ignore[no-untyped-def]
    switch, pipeline, backend = switch
    before = pipeline.anchors.version
    backend.fail_on = "asphalt"
    anchors, error, _ = swap_and_wait(switch.submit, TWO.model_dump_json().encode())
    assert anchors is None and isinstance(error, RuntimeError)
    assert pipeline.anchors.version == before
    assert [entry.version for entry in switch.history().entries] == [before]

    anchors, error, _ = swap_and_wait(switch.submit, b"anchors: [{concept: mud, position: 1.5}]")
    assert anchors is None and isinstance(error, AnchorSetError) and "position" in str(error)
    assert pipeline.anchors.version == before


def test_a_store_that_does_not_answer_refuses_the_swap_in_one_line(switch, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    switch, pipeline, _ = switch
    before = pipeline.anchors.version

    def unreachable(*_: object, **__: object) -> None:
        raise StoreUnavailable("the store db:5432: connection refused")

    monkeypatch.setattr(switch.store, "activate", unreachable)
    anchors, error, _ = swap_and_wait(switch.submit, TWO.model_dump_json().encode())
    assert anchors is None and isinstance(error, AnchorSetError)
    refused = "the anchor store is unreachable (the store db:5432: connection refused): nothing swapped"
    assert str(error) == f"invalid anchor set: {refused}"
    assert pipeline.anchors.version == before and switch.head().version == before


def test_rollback_returns_to_the_set_before(switch) -> None:  # type: ignore[no-untyped-def]
    switch, pipeline, _ = switch
    original = pipeline.anchors.version
    swap_and_wait(switch.submit, TWO.model_dump_json().encode())
    anchors, error, _ = swap_and_wait(switch.submit_rollback, 1)
    assert error is None and anchors is not None and anchors.version == original == pipeline.anchors.version
    assert [(e.version, e.how) for e in switch.history().entries][:2] == [(original, "rollback"), (TWO.version, "set")]
    _, error, _ = swap_and_wait(switch.submit_rollback, 5)
    assert isinstance(error, AnchorSetError) and "no set 5 step(s) back" in str(error)


def test_a_store_away_at_start_is_synced_from_once_it_answers(tmp_path: Path) -> None:
    """A database down when the instance starts: it serves its start set; once the store answers, ``sync``
    (the service's watchdog calls it) installs the set the store holds, once."""
    store = SqliteStore(tmp_path / "store.sqlite3")
    store.seed(TWO, "box-a")  # the fleet's set, recorded before this instance started
    reachable = threading.Event()

    def store_of() -> SqliteStore:
        if not reachable.is_set():
            raise StoreUnavailable("the store db:5432: connection refused")
        return store

    pipeline = Pipeline(ThreadRecordingBackend(), default_anchor_set(), EngineSettings())
    switch = AnchorSwitch(pipeline, store_of, "box-b", 65536)
    told: list[str] = []
    switch.on_change(lambda head: told.append(head.version))
    assert switch.head().version == default_anchor_set().version
    assert switch.sync(lambda anchors, error: None) is False  # still away: nothing to do yet
    reachable.set()
    anchors, error, _ = swap_and_wait(switch.sync)
    assert error is None and anchors == TWO and pipeline.anchors == TWO and told == [TWO.version]
    assert switch.sync(lambda anchors, error: None) is False  # once
    assert [entry.how for entry in switch.history().entries] == ["seeded"]  # nothing recorded twice
    switch.close()
    store.close()
