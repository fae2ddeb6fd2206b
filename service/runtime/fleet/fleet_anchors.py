"""One anchor set per fleet: which active set each live instance announces, and which one wins. No middleware.

Every instance announces its active set as (accepted_at, version): when the set was accepted in the fleet
(a swap's time, kept when another instance adopts it) and its content hash. The newest announcement wins,
by accepted_at, then version as the tie-breaker; an instance whose active version differs from the winner's
adopts the winner's set, with the winner's accepted_at, so that adopting never makes a set look newer. A set
an instance only started with (configured, default) has accepted_at 0: it loses to any accepted one.

Consistency: eventual, last-writer-wins by the swap's wall-clock time. Two swaps to different sets at about
the same moment on different instances resolve to the later one (ties: the larger version) everywhere.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass


@dataclass(frozen=True, order=True)
class ActiveSet:
    accepted_ms: int  # when the set was accepted in the fleet, ms since the epoch; 0: never (a start set)
    version: str

    @classmethod
    def of(cls, accepted_at: float, version: str) -> ActiveSet:
        return cls(round(accepted_at * 1000), version)


class FleetAnchors:
    """The active sets announced by the live instances (this one included); thread-safe."""

    def __init__(self, instance: str) -> None:
        self.instance = instance
        self._announced: dict[str, ActiveSet] = {}
        self._lock = threading.Lock()

    def announced(self, instance: str, active: ActiveSet) -> None:
        with self._lock:
            self._announced[instance] = active

    def withdrawn(self, instance: str, active: ActiveSet) -> None:
        """A token went: forget it unless the instance has announced another since (a swap re-declares)."""
        with self._lock:
            if self._announced.get(instance) == active:
                del self._announced[instance]

    def versions(self) -> dict[str, str]:
        with self._lock:
            return {instance: active.version for instance, active in sorted(self._announced.items())}

    def newest(self) -> tuple[str, ActiveSet] | None:
        with self._lock:
            if not self._announced:
                return None
            return max(self._announced.items(), key=lambda item: (item[1], item[0]))

    def to_adopt(self, own: ActiveSet) -> tuple[str, ActiveSet] | None:
        """The instance and set to adopt: the newest announcement, if it is newer than ``own`` and another set."""
        newest = self.newest()
        if newest is None or newest[1].version == own.version or newest[1] <= own:
            return None
        return newest
