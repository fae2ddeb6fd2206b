"""`gcdtrav serve` with injectable faults, for benchmarks/faults.py (repo tooling, not in the wheel).
The variables are not GCDTRAV_*: those are the service's settings.

    python -m tools.faulty_serve serve --model ... [gcdtrav serve arguments]

FAULTY_SERVE_HANG_FLAG=PATH: while the file PATH exists, inference blocks (a hung worker; the process stays alive).
FAULTY_SERVE_FULL_DIR=DIR: writes of the anchor state under DIR fail with ENOSPC (a full disk, without root mounts).
FAULTY_SERVE_FRAME_COST_S=S: a TEST BACKEND: every inference takes at least S seconds, the rest slept, not computed
(benchmarks/autoscale.py: capacity then grows with the instances, even on a 2-core machine; its maps are the
tiny model's, its speed says nothing about gcdtrav's).
Everything else is the real `gcdtrav serve`.
"""

from __future__ import annotations

import errno
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
    from gcdtrav.service.runtime.fleet import anchor_switch, state

    real_write = state.write_atomically

    def write_atomically(path: Path, text: str | bytes) -> None:
        if Path(path).resolve().is_relative_to(directory.resolve()):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        real_write(path, text)

    state.write_atomically = write_atomically  # save_anchor_state looks it up here
    anchor_switch.write_atomically = write_atomically  # the history file


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
