"""Start-up with a state dir that is full, unwritable, unreachable or corrupt: the service serves the configured
(or last good) set with one clear log line, never a traceback. Root ignores chmod, so "unwritable" is a state
dir under a regular file here, and a full disk is ENOSPC from a patched write."""

from __future__ import annotations

import errno
import logging
import os
from pathlib import Path

import pytest
from fakes import pipeline
from gcdtrav.schemas.anchors import AnchorSet, default_anchor_set
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.commands.serve import starting_anchor_set
from gcdtrav.service.runtime.fleet import state
from gcdtrav.service.runtime.fleet.anchor_switch import AnchorSwitch

TWO = AnchorSet.model_validate(
    {"anchors": [{"concept": "water", "position": 0.0}, {"concept": "road", "position": 1.0}]}
)


def unreachable_state_dir(tmp_path: Path) -> Path:
    blocker = tmp_path / "state-is-a-file"
    blocker.write_text("not a directory")
    return blocker / "gcdtrav"


def test_an_unreachable_state_dir_starts_on_the_configured_set_and_refuses_swaps_cleanly(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    settings = ServiceSettings(state_dir=unreachable_state_dir(tmp_path))
    with caplog.at_level(logging.ERROR, "gcdtrav.service"):
        assert starting_anchor_set(settings).version == default_anchor_set().version
        switch = AnchorSwitch(pipeline(), settings.state_file, "box-1", 65536)
    assert "cannot write the anchor history" in caplog.text and "swaps will fail" in caplog.text
    assert switch.head().version == default_anchor_set().version
    with pytest.raises(OSError):
        switch.swap(TWO)
    assert switch.pipeline.anchors.version == default_anchor_set().version
    switch.close()


def test_a_state_dir_that_is_itself_a_file_or_holds_garbage_is_one_log_line(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    as_file = tmp_path / "state"
    as_file.write_text("x")
    with caplog.at_level(logging.ERROR):
        assert state.load_anchor_state(as_file / "gcdtrav.anchors.json") is None
    corrupt = tmp_path / "ok" / "gcdtrav.anchors.json"
    corrupt.parent.mkdir()
    corrupt.write_bytes(b"\xff\xfe{ not json")
    with caplog.at_level(logging.ERROR):
        assert state.load_anchor_state(corrupt) is None
    assert "ignoring the anchor state file" in caplog.text
    directory = tmp_path / "dir" / "gcdtrav.anchors.json"
    directory.mkdir(parents=True)  # something that is not a file where the state file goes
    assert state.load_anchor_state(directory) is None


def test_a_full_disk_at_start_serves_the_persisted_set_and_a_swap_keeps_the_active_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    state_file = tmp_path / "gcdtrav.anchors.json"
    state.save_anchor_state(state_file, TWO)  # the last good set, written before the disk filled up
    settings = ServiceSettings(state_dir=tmp_path)

    def full(fd: int) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(state.os, "fsync", full)
    assert starting_anchor_set(settings).version == TWO.version
    run = pipeline()
    run.activate(run.prepare(TWO))
    with caplog.at_level(logging.ERROR, "gcdtrav.service"):
        switch = AnchorSwitch(run, settings.state_file, "box-1", 65536)  # the history cannot be written
    assert "No space left on device" in caplog.text
    with pytest.raises(OSError):
        switch.swap(default_anchor_set())
    assert run.anchors.version == TWO.version
    assert state.load_anchor_state(state_file) is not None
    assert state.load_anchor_state(state_file).version == TWO.version  # type: ignore[union-attr]
    assert not list(tmp_path.glob(".*.tmp"))  # failed writes leave no temporaries
    switch.close()
