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
from gcdtrav.service.pipeline import Pipeline
from gcdtrav.service.runtime.anchor_switch import AnchorSwitch
from gcdtrav.service.runtime.state import load_anchor_state
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
    state = load_anchor_state(switch.state_file)
    assert pipeline.anchors.version == before and state is not None and state.version == before
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
    """What a restarted service serves, and its switch (which repairs the mirror)."""
    from gcdtrav.service.runtime.anchor_switch import persisted_anchor_set

    anchors = persisted_anchor_set(state_file) or default_anchor_set()
    return anchors, AnchorSwitch(Pipeline(ThreadRecordingBackend(), anchors, EngineSettings()), state_file, "b", 65536)


def test_a_crash_between_the_history_and_the_state_file_restarts_consistent(switch, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """Killed after the commit point (the history) and before the mirror (the state file): the restart serves
    the swapped set, and history and state agree on it."""
    switch, _, _ = switch

    class Killed(BaseException):
        pass

    def killed(*_: object) -> None:
        raise Killed

    monkeypatch.setattr("gcdtrav.service.runtime.anchor_switch.save_anchor_state", killed)
    with pytest.raises(Killed):
        switch.swap(TWO)
    monkeypatch.undo()
    assert load_anchor_state(switch.state_file) == default_anchor_set()  # the mirror is behind
    anchors, restarted = restart(switch.state_file)
    assert anchors.version == TWO.version
    assert restarted.history().entries[0].version == TWO.version
    assert load_anchor_state(switch.state_file) == TWO  # repaired
    restarted.close()


def test_a_refused_history_write_refuses_the_swap_and_survives_a_restart(switch, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """A full disk: the history cannot be written, so the swap is refused, nothing changes, and a restart
    serves the set that was active, never the refused one."""
    switch, pipeline, _ = switch
    before = pipeline.anchors

    def full_disk(*_: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("gcdtrav.service.runtime.anchor_switch.write_atomically", full_disk)
    anchors, error, _ = swap_and_wait(switch.submit, TWO.model_dump_json().encode())
    monkeypatch.undo()
    assert anchors is None and isinstance(error, OSError)
    assert pipeline.anchors == before and load_anchor_state(switch.state_file) == before
    assert restart(switch.state_file)[0] == before


def test_a_state_file_of_a_version_before_1_1_is_still_read(tmp_path: Path) -> None:
    from gcdtrav.service.runtime.anchor_switch import persisted_anchor_set
    from gcdtrav.service.runtime.state import save_anchor_state

    save_anchor_state(tmp_path / "anchors.json", TWO)  # no history file beside it
    assert persisted_anchor_set(tmp_path / "anchors.json") == TWO
