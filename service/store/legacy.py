"""The files the store replaces, imported once at the first start with a store (issue 46): the msgpack
experience file ({prefix}.experience.msgpack, format 1) and the anchor state ({prefix}.anchors.json, the
active set) with its history ({prefix}.anchors-history.json). An imported file is kept, renamed with
``IMPORTED_SUFFIX``, so a second start does not import it twice and an operator can still look at it.

An unreadable file is one log line and stays where it is; the service starts without its content, as before."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
from gcdtrav.schemas.anchors import AnchorSet, AnchorSetError
from gcdtrav.schemas.messages import AnchorHistoryEntry, AnchorHistoryReply, MessageError
from gcdtrav.service.store.base import Store
from gcdtrav.service.store.records import PairRecord

log = logging.getLogger("gcdtrav.service")
IMPORTED_SUFFIX = ".imported"
EXPERIENCE_FILE_FORMAT = 1
NO_BOUND = 2**62  # the import keeps every pair the file held; the next append applies the bounds


def experience_file(state_dir: Path, prefix: str) -> Path:
    """Where the msgpack store of an instance before issue 46 kept its pairs."""
    return state_dir / f"{prefix.replace('/', '_')}.experience.msgpack"


def history_file_of(state_file: Path) -> Path:
    """The anchor history next to the anchor state file."""
    return state_file.with_name(state_file.name.removesuffix(".json") + "-history.json")


def imported_name(path: Path) -> Path:
    return path.with_name(path.name + IMPORTED_SUFFIX)


def read_experience_file(path: Path, source: str, instance: str) -> list[PairRecord]:
    """Every pair of a format-1 msgpack experience file, oldest first; ValueError if it is not one."""
    document: Any = msgpack.unpackb(path.read_bytes(), raw=False)
    if not isinstance(document, dict) or document.get("format") != EXPERIENCE_FILE_FORMAT:
        found = document.get("format") if isinstance(document, dict) else type(document).__name__
        raise ValueError(f"format {found!r}, this reader reads {EXPERIENCE_FILE_FORMAT}")
    ordered: list[tuple[int, PairRecord]] = []
    for item in document["buckets"]:
        concepts = tuple(str(c) for c in item["concepts"])
        weights = np.frombuffer(item["weights"], "<f4").reshape(-1, len(concepts))
        outcomes, stamps = np.frombuffer(item["outcomes"], "<f8"), np.frombuffer(item["stamps"], "<f8")
        kinds, index = np.frombuffer(item["kinds"], "u1"), np.frombuffer(item["version_index"], "<u2")
        sequence = np.frombuffer(item["sequence"], "<i8")
        if not len(weights) == len(outcomes) == len(stamps) == len(kinds) == len(index) == len(sequence):
            raise ValueError(f"the columns of {list(concepts)} differ in length")
        versions = [str(v) for v in item["versions"]]
        for k in range(len(outcomes)):
            record = PairRecord(concepts, weights[k].copy(), float(outcomes[k]), float(stamps[k]), int(kinds[k]),
                                versions[int(index[k])], source, instance)  # fmt: skip
            ordered.append((int(sequence[k]), record))
    ordered.sort(key=lambda item: item[0])
    return [record for _, record in ordered]


def import_experience_file(store: Store, path: Path, source: str, instance: str) -> int:
    """Append the file's pairs (as pairs of ``source``, the grid it collected) and rename it; the pairs
    imported (0 with no file, or an unreadable one, logged and left in place)."""
    if not path.is_file():
        return 0
    try:
        records = read_experience_file(path, source, instance)
    except (OSError, ValueError, KeyError, TypeError, IndexError, msgpack.UnpackException) as err:
        log.error("cannot import the experience file %s: %s; left in place, starting without its pairs", path, err)
        return 0
    store.append_pairs(records, NO_BOUND, NO_BOUND)
    _rename(path)
    log.info("imported %d pairs from %s into the store %s", len(records), path, store.location)
    return len(records)


def import_anchor_state(store: Store, state_file: Path, instance: str, rename: bool = True) -> int:
    """Into a store without an active set: the history file's sets (oldest first) and the state file's set as
    the active one, each marked ``imported``; the entries written. Files renamed when ``rename``."""
    if store.active() is not None or not state_file.is_file():
        return 0
    history_file = history_file_of(state_file)
    try:
        active = AnchorSet.load(state_file)
    except (AnchorSetError, OSError) as err:
        log.error("cannot import the anchor state %s: %s; left in place", state_file, err)
        return 0
    entries = _history_entries(history_file)
    if not entries or entries[0].version != active.version:
        entries = [AnchorHistoryEntry(accepted_at=0.0, version=active.version, anchor_set=active), *entries]
    for entry in reversed(entries):  # oldest first: the active set is written last and stays active
        store.activate(entry.anchor_set, None, "imported", instance, accepted_at=entry.accepted_at)
    if rename:
        for path in (state_file, history_file):
            _rename(path)
    log.info("imported anchor set %s and %d history entries into the store", active.version, len(entries))
    return len(entries)


def _history_entries(history_file: Path) -> list[AnchorHistoryEntry]:
    if not history_file.is_file():
        return []
    try:
        return AnchorHistoryReply.model_validate_json(history_file.read_text("utf-8")).entries
    except (OSError, ValueError, MessageError) as err:
        log.error("cannot import the anchor history %s: %s; importing the active set only", history_file, err)
        return []


def _rename(path: Path) -> None:
    if not path.exists():
        return
    try:
        path.replace(imported_name(path))
    except OSError as err:  # a read-only state dir: serve anyway; a next start imports the file again
        log.error("imported %s but cannot rename it (%s): the next start imports it again", path, err.strerror or err)
