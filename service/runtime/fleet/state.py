"""The accepted anchor set on disk: written atomically so a crash never leaves a torn file."""

from __future__ import annotations

import logging
import os
import tempfile
from pathlib import Path

from gcdtrav.schemas.anchors import AnchorSet, AnchorSetError

log = logging.getLogger(__name__)


def write_atomically(path: Path, text: str | bytes) -> None:
    """Write to a temporary file in the same folder, fsync it, rename over ``path``, fsync the folder."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(text.encode("utf-8") if isinstance(text, str) else text)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    directory = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(directory)
    finally:
        os.close(directory)


def save_anchor_state(path: Path, anchors: AnchorSet) -> None:
    write_atomically(path, anchors.to_json() + "\n")


def remove_stale_temporaries(path: Path) -> None:
    """Temporary files of writes a crash interrupted (``path`` itself is intact); best effort: a read-only
    state dir keeps them, and says so."""
    try:
        for stale in path.parent.glob(f".{path.name}.*.tmp"):
            stale.unlink(missing_ok=True)
    except OSError as err:
        log.warning("cannot remove interrupted writes next to %s: %s", path, err.strerror or err)


def load_anchor_state(path: Path) -> AnchorSet | None:
    """The persisted set, or None if there is none or it is unusable (then the configured set is used): a
    corrupt, unreadable or unreachable state file is one log line, never a failed start."""
    try:
        if path.parent.is_dir():
            remove_stale_temporaries(path)
        if not path.is_file():
            return None
        return AnchorSet.load(path)
    except AnchorSetError as err:
        log.error("ignoring the anchor state file: %s; serving the configured set", err)
    except OSError as err:
        log.error("cannot read the anchor state file %s: %s; serving the configured set", path, err.strerror or err)
    return None
