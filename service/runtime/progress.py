"""Is the worker making progress? Liveness by progress, not by the process being alive. No middleware here.

A process whose inference hangs keeps its zenoh session, so its liveliness token stays and its robots are
never failed over. The inference worker beats (``beat``) each time round its loop and after each step of
a frame, also when idle (the glance answering unchanged views does not: a hung inference must be seen while
parked robots are still answered); ``check`` calls an instance *stalled* when work is queued or in flight
and no beat came for ``stall_after_s``. The bus then withdraws the instance's token (its sources fail
over) and reports it unhealthy; the first beat after that is progress again and the instance rejoins.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class Health:
    healthy: bool
    reason: str = ""


@dataclass(frozen=True)
class Change:
    """A transition ``check`` saw: the new health (the bus withdraws or rejoins on it)."""

    health: Health


class ProgressMonitor:
    """Thread-safe: beaten by the worker threads, checked by the bus's watchdog."""

    def __init__(self, stall_after_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.stall_after_s = stall_after_s
        self._clock = clock
        self._lock = threading.Lock()
        self._last_beat = clock()
        self._stalled_since: float | None = None
        self._reason = ""

    def beat(self) -> None:
        with self._lock:
            self._last_beat = self._clock()

    def check(self, queued: int) -> Change | None:
        """The health now, if it changed since the last check; ``queued`` frames wait for inference."""
        with self._lock:
            now = self._clock()
            silent_s = now - self._last_beat
            if self._stalled_since is None:
                if queued > 0 and silent_s > self.stall_after_s:
                    self._stalled_since = now
                    self._reason = (
                        f"stalled: no progress for {silent_s:.1f} s (stall_after_s {self.stall_after_s:g}) "
                        f"with {queued} frame(s) queued"
                    )
                    return Change(Health(False, self._reason))
                return None
            if self._last_beat > self._stalled_since:  # progress since the stall was declared
                stalled_for = now - self._stalled_since
                self._stalled_since, self._reason = None, ""
                return Change(Health(True, f"progressing again after {stalled_for:.1f} s"))
            return None

    def health(self) -> Health:
        with self._lock:
            return Health(self._stalled_since is None, self._reason)
