"""`gcdtrav serve` with injectable faults, for benchmarks/faults.py (repo tooling, not in the wheel).
The variables are not GCDTRAV_*: those are the service's settings.

    python -m tools.faulty_serve serve --model ... [gcdtrav serve arguments]

FAULTY_SERVE_HANG_FLAG=PATH: while the file PATH exists, inference blocks (a hung worker; the process stays alive).
FAULTY_SERVE_FULL_DIR=DIR: writes under DIR (files, and the SQLite store's transactions) fail as on a full disk
(ENOSPC, 'database or disk is full'), without root mounts.
FAULTY_SERVE_FRAME_COST_S=S: a TEST BACKEND: every inference takes at least S seconds, the rest slept, not computed
(benchmarks/autoscale.py: capacity then grows with the instances, even on a 2-core machine; its maps are the
tiny model's, its speed says nothing about gcdtrav's).
Everything else is the real `gcdtrav serve`.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path
from typing import Any


def hang_while_flagged(flag: Path) -> None:
    from gcdtrav.service.backends.clipseg import ClipSegBackend

    real_logits = ClipSegBackend.logits

    def logits(self: ClipSegBackend, image_rgb: Any, prepared: object) -> Any:
        while flag.exists():
            time.sleep(0.02)
        return real_logits(self, image_rgb, prepared)

    setattr(ClipSegBackend, "logits", logits)  # noqa: B010 (a method patched for the fault; mypy versions disagree on method-assign)


def fixed_frame_cost(seconds: float) -> None:
    from gcdtrav.service.backends.clipseg import ClipSegBackend

    real_logits = ClipSegBackend.logits

    def logits(self: ClipSegBackend, image_rgb: Any, prepared: object) -> Any:
        began = time.monotonic()
        result = real_logits(self, image_rgb, prepared)
        time.sleep(max(0.0, seconds - (time.monotonic() - began)))
        return result

    setattr(ClipSegBackend, "logits", logits)  # noqa: B010 (as above)


def fail_writes_under(directory: Path) -> None:
    from gcdtrav.service.store import StoreUnavailable
    from gcdtrav.service.store.sqlite import SqliteStore

    real_transaction = SqliteStore._transaction

    def under(path: Path) -> bool:
        return Path(path).resolve().is_relative_to(directory.resolve())

    def transaction(self: SqliteStore, lock: Any) -> Any:
        if lock is not None and under(self.path):  # a write: what SQLite says on a full disk
            raise StoreUnavailable(f"the store {self.path}: database or disk is full")
        return real_transaction(self, lock)

    setattr(SqliteStore, "_transaction", transaction)  # noqa: B010 (as above): the store's writes, the only ones


def main() -> int:
    if flag := os.environ.get("FAULTY_SERVE_HANG_FLAG"):
        hang_while_flagged(Path(flag))
    if full := os.environ.get("FAULTY_SERVE_FULL_DIR"):
        fail_writes_under(Path(full))
    if cost := os.environ.get("FAULTY_SERVE_FRAME_COST_S"):
        fixed_frame_cost(float(cost))
    from gcdtrav.service.commands.cli import main as serve_main

    return serve_main()


if __name__ == "__main__":
    sys.exit(main())
