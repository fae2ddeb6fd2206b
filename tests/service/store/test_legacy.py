"""The files of gcdtrav before the store (written by that version's own code: legacy_files/write_them.py) are
imported once, on both backends: every pair in its order, its tuple and version; the anchor history with the
active set last; the files kept, renamed. An unreadable file stays put and costs one log line."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import msgpack
import numpy as np
import pytest
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.store import Store
from gcdtrav.service.store.legacy import (
    IMPORTED_SUFFIX,
    experience_file,
    import_anchor_state,
    import_experience_file,
    read_experience_file,
)
from gcdtrav.service.store.opening import service_outbox, sqlite_file

FILES = Path(__file__).resolve().parent / "legacy_files"
PAIRS_WRITTEN = 1250  # 250 outcomes x 5 cells (write_them.py)


def state_dir_with_old_files(tmp_path: Path) -> Path:
    state = tmp_path / "state"
    state.mkdir()
    for name in ("gcdtrav.experience.msgpack", "gcdtrav.anchors.json", "gcdtrav.anchors-history.json"):
        shutil.copy(FILES / name, state / name)
    return state


def test_the_old_pairs_come_in_once_in_order_and_the_file_is_kept_renamed(store: Store, tmp_path: Path) -> None:
    state = state_dir_with_old_files(tmp_path)
    path = experience_file(state, "gcdtrav")
    document = msgpack.unpackb(path.read_bytes(), raw=False)
    assert import_experience_file(store, path, "cam", "i1") == PAIRS_WRITTEN
    assert not path.exists() and path.with_name(path.name + IMPORTED_SUFFIX).is_file()
    assert import_experience_file(store, path, "cam", "i1") == 0  # a second start: nothing to import
    assert store.totals().pairs == PAIRS_WRITTEN
    assert store.tuples() == [("asphalt", "rock", "sand"), ("grass", "mud")]
    two = store.pairs(["mud", "grass"])
    assert len(two) == 900 and len(set(two.versions)) == 2 and set(two.sources) == {"cam"}
    assert list(two.stamps) == sorted(two.stamps)  # oldest first, as the file's sequence said
    bucket = next(b for b in document["buckets"] if b["concepts"] == ["grass", "mud"])
    np.testing.assert_array_equal(two.weights, np.frombuffer(bucket["weights"], "<f4").reshape(-1, 2))
    np.testing.assert_array_equal(two.outcomes, np.frombuffer(bucket["outcomes"], "<f8"))


def test_the_anchor_history_comes_in_with_the_active_set_last(store: Store, tmp_path: Path) -> None:
    state = state_dir_with_old_files(tmp_path)
    active = AnchorSet.load(state / "gcdtrav.anchors.json")
    assert import_anchor_state(store, state / "gcdtrav.anchors.json", "i1", rename=True) == 3
    history = store.history()
    assert [h.how for h in history] == ["imported"] * 3
    assert history[0].version == active.version and store.active() == history[0]
    assert history[-1].accepted_at == 1700000000.0
    assert not (state / "gcdtrav.anchors.json").exists()
    assert (state / f"gcdtrav.anchors-history.json{IMPORTED_SUFFIX}").is_file()
    shutil.copy(FILES / "gcdtrav.anchors.json", state / "gcdtrav.anchors.json")
    assert import_anchor_state(store, state / "gcdtrav.anchors.json", "i2") == 0  # a set is active: never again


def test_an_unreadable_experience_file_stays_and_is_one_log_line(
    store: Store, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "gcdtrav.experience.msgpack"
    path.write_bytes(b"\x93not what we wrote")
    with caplog.at_level(logging.ERROR):
        assert import_experience_file(store, path, "cam", "i1") == 0
    assert path.is_file() and store.totals().pairs == 0
    assert len([r for r in caplog.records if "cannot import the experience file" in r.message]) == 1
    with pytest.raises(ValueError, match="format 7"):
        path.write_bytes(msgpack.packb({"format": 7, "buckets": []}))
        read_experience_file(path, "cam", "i1")


def test_a_first_start_with_defaults_imports_into_sqlite_in_the_state_dir(tmp_path: Path) -> None:
    """`gcdtrav serve` with no store setting: SQLite in the state dir, the old pairs and anchor sets in it; the
    anchor files renamed (the store is their record now; the anchor switch reads the store)."""
    state = state_dir_with_old_files(tmp_path)
    settings = ServiceSettings.model_validate({"state_dir": state})
    outbox = service_outbox(settings)
    try:
        assert outbox.state().reachable and outbox.location == str(sqlite_file(state, "gcdtrav"))
        assert outbox.store is not None and outbox.store.totals().pairs == PAIRS_WRITTEN
        assert outbox.store.active() is not None and outbox.store.active().how == "imported"  # type: ignore[union-attr]
        assert not (state / "gcdtrav.anchors.json").exists()
        assert (state / f"gcdtrav.anchors.json{IMPORTED_SUFFIX}").is_file()
    finally:
        outbox.close()
    again = service_outbox(settings)  # a restart imports nothing twice
    try:
        assert again.store is not None and again.store.totals().pairs == PAIRS_WRITTEN
        assert len(again.store.history()) == 3
    finally:
        again.close()
