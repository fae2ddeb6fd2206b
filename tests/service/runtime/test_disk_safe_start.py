"""Start-up with a store that does not answer or a state dir that is corrupt: the service serves the set it
started with (configured, or last good) with one clear log line, never a traceback, and refuses swaps in one
line until the store answers."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
from fakes import pipeline
from gcdtrav.schemas.anchors import AnchorSet, AnchorSetError, default_anchor_set
from gcdtrav.service.runtime.fleet.anchor_switch import AnchorSwitch
from gcdtrav.service.store import StoreUnavailable
from gcdtrav.service.store.legacy import import_anchor_state
from gcdtrav.service.store.sqlite import SqliteStore

TWO = AnchorSet.model_validate(
    {"anchors": [{"concept": "water", "position": 0.0}, {"concept": "road", "position": 1.0}]}
)


def unreachable_state_dir(tmp_path: Path) -> Path:
    blocker = tmp_path / "state-is-a-file"
    blocker.write_text("not a directory")
    return blocker / "gcdtrav"


@pytest.mark.parametrize("failure", ["connection refused", "database or disk is full"])
def test_a_store_that_does_not_answer_at_start_serves_the_start_set_and_refuses_swaps_cleanly(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture, failure: str
) -> None:
    store = SqliteStore(tmp_path / "store.sqlite3")

    def unavailable(*_: object, **__: object) -> None:
        raise StoreUnavailable(f"the store db: {failure}")

    for method in ("active", "seed", "activate", "history"):
        monkeypatch.setattr(store, method, unavailable)
    run = pipeline()
    run.activate(run.prepare(TWO))  # the set it was started with (configured, or the last good one)
    with caplog.at_level(logging.ERROR, "gcdtrav.service"):
        switch = AnchorSwitch(run, store, "box-1", 65536)
    assert f"the store db: {failure}; serving anchor set {TWO.version} until it answers" in caplog.text
    assert switch.head().version == TWO.version
    with pytest.raises(AnchorSetError, match="the anchor store is unreachable"):
        switch.swap(default_anchor_set())
    assert switch.pipeline.anchors.version == TWO.version
    assert [entry.version for entry in switch.history().entries] == [TWO.version]  # from memory
    switch.close()
    store.close()


def test_an_old_state_file_that_is_garbage_or_not_a_file_is_one_log_line_and_not_imported(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    store = SqliteStore(tmp_path / "store.sqlite3")
    as_file = tmp_path / "state"
    as_file.write_text("x")
    assert import_anchor_state(store, as_file / "gcdtrav.anchors.json", "box-1") == 0  # its folder is a file
    corrupt = tmp_path / "ok" / "gcdtrav.anchors.json"
    corrupt.parent.mkdir()
    corrupt.write_bytes(b"\xff\xfe{ not json")
    with caplog.at_level(logging.ERROR):
        assert import_anchor_state(store, corrupt, "box-1") == 0
    assert "cannot import the anchor state" in caplog.text and corrupt.is_file()  # left in place
    directory = tmp_path / "dir" / "gcdtrav.anchors.json"
    directory.mkdir(parents=True)  # something that is not a file where the state file goes
    assert import_anchor_state(store, directory, "box-1") == 0 and store.active() is None
    store.close()
