"""AnchorSwitch without a bus: swaps run on its own worker (never the caller's thread, which in the service
is zenoh's callback), each step in order, and a failing step leaves the active set, the state file and
the history as they were."""

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
from gcdtrav.service.runtime.fleet.state import load_anchor_state
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
    assert reported.wait(10), "the swap never reported"
    return result[0], result[1], result[2]  # type: ignore[return-value]


@pytest.fixture
def switch(tmp_path: Path):  # type: ignore[no-untyped-def]
    backend = ThreadRecordingBackend()
    pipeline = Pipeline(backend, default_anchor_set(), EngineSettings())
    (tmp_path / "state").mkdir()
    switch = AnchorSwitch(pipeline, tmp_path / "state" / "anchors.json", "test", max_body_bytes=65536)
    yield switch, pipeline, backend
    switch.close()


def test_a_swap_runs_on_the_worker_and_persists_before_it_activates(switch) -> None:  # type: ignore[no-untyped-def]
    switch, pipeline, backend = switch
    anchors, error, reporter = swap_and_wait(switch.submit, TWO.model_dump_json().encode())
    assert error is None and anchors is not None and anchors.version == TWO.version
    caller = threading.current_thread().name
    assert backend.prepared_on[-1] == (reporter, ("water", "asphalt"))  # prepared where it reported
    assert reporter.startswith("gcdtrav-anchors") and reporter != caller
    assert pipeline.anchors.version == TWO.version
    state = load_anchor_state(switch.state_file)
    assert state is not None and state.version == TWO.version
    assert [entry.version for entry in switch.history().entries] == [TWO.version, default_anchor_set().version]


def test_a_failed_swap_changes_nothing(switch) -> None:  # type: ignore[no-untyped-def]
    switch, pipeline, backend = switch
    before = pipeline.anchors.version
    backend.fail_on = "asphalt"
    anchors, error, _ = swap_and_wait(switch.submit, TWO.model_dump_json().encode())
    assert anchors is None and isinstance(error, RuntimeError)
    assert pipeline.anchors.version == before and not switch.state_file.exists()
    assert [entry.version for entry in switch.history().entries] == [before]

    anchors, error, _ = swap_and_wait(switch.submit, b"anchors: [{concept: mud, position: 1.5}]")
    assert anchors is None and isinstance(error, AnchorSetError) and "position" in str(error)
    assert pipeline.anchors.version == before


def test_rollback_returns_to_the_set_before(switch) -> None:  # type: ignore[no-untyped-def]
    switch, pipeline, _ = switch
    original = pipeline.anchors.version
    swap_and_wait(switch.submit, TWO.model_dump_json().encode())
    anchors, error, _ = swap_and_wait(switch.submit_rollback, 1)
    assert error is None and anchors is not None and anchors.version == original == pipeline.anchors.version
    _, error, _ = swap_and_wait(switch.submit_rollback, 5)
    assert isinstance(error, AnchorSetError) and "no set 5 step(s) back" in str(error)


def restart(state_file: Path) -> tuple[AnchorSet, AnchorSwitch]:
    """What a restarted service serves (the state file, else the default), and its switch."""
    anchors = load_anchor_state(state_file) or default_anchor_set()
    return anchors, AnchorSwitch(Pipeline(ThreadRecordingBackend(), anchors, EngineSettings()), state_file, "b", 65536)


class Killed(BaseException):
    """The process dies here: nothing after it runs, nothing catches it."""


def test_a_crash_between_the_history_and_the_state_file_restarts_consistent(switch, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """Killed after the history and before the commit point (the state file): the swap was never acknowledged;
    the restart serves the old set and the history names it first again."""
    switch, pipeline, _ = switch
    before = pipeline.anchors

    def killed(*_: object) -> None:
        raise Killed

    monkeypatch.setattr("gcdtrav.service.runtime.fleet.anchor_switch.save_anchor_state", killed)
    with pytest.raises(Killed):
        switch.swap(TWO)
    monkeypatch.undo()
    anchors, restarted = restart(switch.state_file)
    assert anchors == before
    assert restarted.history().entries[0].version == before.version
    restarted.close()


@pytest.mark.parametrize("failing", ["history", "state"])
def test_a_refused_write_refuses_the_swap_and_survives_a_restart(switch, monkeypatch, failing: str) -> None:  # type: ignore[no-untyped-def]
    """A full disk at either write: the swap is refused, nothing changes, the history does not name the refused
    set, and a restart serves the set that was active, never the refused one."""
    switch, pipeline, _ = switch
    before = pipeline.anchors
    real_write = __import__("gcdtrav.service.runtime.fleet.state", fromlist=["x"]).write_atomically

    def full_disk(path: Path, text: str) -> None:
        if (failing == "history") == (path == switch.history_file):
            raise OSError(28, "No space left on device")
        real_write(path, text)

    monkeypatch.setattr("gcdtrav.service.runtime.fleet.anchor_switch.write_atomically", full_disk)
    monkeypatch.setattr("gcdtrav.service.runtime.fleet.state.write_atomically", full_disk)
    anchors, error, _ = swap_and_wait(switch.submit, TWO.model_dump_json().encode())
    monkeypatch.undo()
    assert anchors is None and isinstance(error, OSError)
    assert pipeline.anchors == before and load_anchor_state(switch.state_file) in (None, before)
    assert [entry.version for entry in switch.history().entries] == [before.version]
    anchors, restarted = restart(switch.state_file)
    assert anchors == before and restarted.history().entries[0].version == before.version
    restarted.close()
