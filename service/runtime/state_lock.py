"""One service per state file: an exclusive lock held for the service's life.

The state file (the accepted anchor set) and its history are named by prefix, not by instance, so that a
restarted process finds them (its default instance name holds its pid). Per-instance files would lose that;
two instances writing one history would lose each other's entries. So a lock, not per-instance files: the
second ``gcdtrav serve`` on one state directory and prefix refuses to start, naming the first and the fix.
``flock`` locks go with the process: a killed service leaves no stale lock behind.
"""

from __future__ import annotations

import fcntl
import logging
import os
from pathlib import Path
from typing import BinaryIO

from gcdtrav.schemas.settings import SettingsError

log = logging.getLogger("gcdtrav.service")


def lock_file_of(state_file: Path) -> Path:
    return state_file.with_name(state_file.name + ".lock")


class StateLock:
    """Held from construction to ``release``; SettingsError when another process or service holds it."""

    def __init__(self, state_file: Path, instance: str) -> None:
        self.path = lock_file_of(state_file)
        self._file: BinaryIO | None = None  # a file object: a service dropped half-built unlocks when collected
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            file = self.path.open("r+b") if self.path.exists() else self.path.open("w+b")
        except OSError as err:  # a read-only state dir: serving matters more (AnchorSwitch says so too)
            log.error("cannot lock the state file %s (%s): make sure no other instance uses it", self.path, err)
            return
        try:
            fcntl.flock(file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = file.read(200).decode("utf-8", "replace").strip() or "another service"
            file.close()
            raise SettingsError(
                f"the state file {state_file} is in use by {holder}: two instances must not share it; give this "
                "one its own --state-dir (or another --prefix)"
            ) from None
        file.truncate(0)
        file.write(f"instance {instance} (pid {os.getpid()})".encode())
        file.flush()
        self._file = file

    def release(self) -> None:
        file, self._file = self._file, None
        if file is not None:
            file.close()  # closing drops the flock
