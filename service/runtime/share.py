"""Which source's frame is inferred next (issue 34). No zenoh here; the queue asks, under its lock.

``RoundRobin``: the source waiting longest goes first: one frame per source in turn, whatever it shows.

``NeedShare``, a weighted fair share over the sources whose frames wait for inference. Each source has a
weight, ``base_weight + motion * (motion_weight + ambiguity_weight * ambiguity)``: motion (0..1) from its
pose's speed, else from how fast its view changes (service/runtime/reuse.py); ambiguity (0..1), the share of
ambiguous (U >= ``ambiguous_u``) or novel (match < ``novel_match``) patches in the lower half of its last
map, the ground ahead of a forward camera. Ambiguity ahead counts as far as the robot moves towards it: a
parked robot's frames are refreshes of a view its maps already describe, and inferring them sooner tells
nobody anything new (measured: with ambiguity counted alone, random weights' ambiguous maps gave 4 parked
robots a third of a 2-core box, benchmarks/README.md). In order:

1. **the floor**: a frame that has waited ``max_wait_s`` goes first (the longest waiting first); when every
   source is over it the rule is round-robin, the fairest there is for an overloaded box;
2. **a changed view after reuse** (urgent: its consumers hold maps of a view that is gone) goes next, but
   takes at most every other turn while other frames wait, so views that keep flipping cannot starve the
   rest;
3. otherwise weighted fair queueing (a virtual clock, as in stride scheduling): each turn a source takes
   costs it ``1 / weight`` of virtual time; the waiting source whose next turn would finish first
   (``max(virtual now, its last finish) + 1 / weight``) goes, and virtual now moves to that turn's start.
   Sources that always wait get turns in proportion to their weights; a source that was not waiting
   (parked, its views reused) comes back at virtual now, neither ahead (no credit banked while idle) nor
   behind. Weights are read at each choice, so a robot that starts moving gets its share at once.
   **Refreshes** (an unchanged view inferred again because its maps are ``max_reuse_s`` old) yield: they
   go only when no other frame waits, or at the floor. A refresh tells something new only if the change
   measure missed a change; every other frame is news. Measured: 4 parked robots refreshing at the base
   weight took a tenth of a 2-core box from 4 moving ones (benchmarks/README.md, *A mixed fleet*).

The queue keeps its own rule on top: a new source's first frame takes at most every other turn.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from gcdtrav.schemas.settings.share import ScheduleSettings
from numpy.typing import NDArray

SHARE_WINDOW_S = 10.0


@dataclass(frozen=True)
class Waiting:
    """A source with a frame ready for inference: since when it waits (its slot filled, monotonic)."""

    source: str
    since: float


@dataclass(frozen=True)
class Share:
    weight: float | None  # None: round-robin has no weights
    share: float  # of the inferences over the last SHARE_WINDOW_S


class SharePolicy(Protocol):
    name: str

    def choose(self, waiting: Sequence[Waiting], now: float) -> str: ...

    def taken(self, source: str, now: float) -> None: ...

    def mark_urgent(self, source: str) -> None: ...

    def mark_refresh(self, source: str, refresh: bool) -> None: ...

    def set_ambiguity(self, source: str, ambiguity: float) -> None: ...

    def shares(self) -> dict[str, Share]: ...

    def forget(self, source: str) -> None: ...


class _TakeLog:
    """The inferences of the last SHARE_WINDOW_S, for each source's measured share."""

    def __init__(self, clock: Callable[[], float]) -> None:
        self.clock = clock
        self._takes: deque[tuple[float, str]] = deque()
        self._lock = threading.Lock()

    def add(self, source: str, now: float) -> None:
        with self._lock:
            self._takes.append((now, source))

    def shares(self) -> dict[str, float]:
        now = self.clock()
        with self._lock:
            while self._takes and self._takes[0][0] < now - SHARE_WINDOW_S:
                self._takes.popleft()
            sources = [source for _, source in self._takes]
        return {source: sources.count(source) / len(sources) for source in set(sources)}

    def forget(self, source: str) -> None:
        with self._lock:
            self._takes = deque(take for take in self._takes if take[1] != source)


class RoundRobin:
    name = "round_robin"

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._log = _TakeLog(clock)

    def choose(self, waiting: Sequence[Waiting], now: float) -> str:
        return min(waiting, key=lambda w: w.since).source

    def taken(self, source: str, now: float) -> None:
        self._log.add(source, now)

    def mark_urgent(self, source: str) -> None:
        pass

    def mark_refresh(self, source: str, refresh: bool) -> None:
        pass

    def set_ambiguity(self, source: str, ambiguity: float) -> None:
        pass

    def shares(self) -> dict[str, Share]:
        return {source: Share(None, round(share, 3)) for source, share in self._log.shares().items()}

    def forget(self, source: str) -> None:
        self._log.forget(source)


class NeedShare:
    name = "need"

    def __init__(
        self,
        settings: ScheduleSettings,
        motion_of: Callable[[str], float] = lambda source: 0.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.settings, self.motion_of = settings, motion_of
        self._log = _TakeLog(clock)
        self._finish: dict[str, float] = {}  # virtual time each source's last turn finished
        self._start: dict[str, float] = {}  # virtual start of a waiting source's next turn, fixed when it began
        self._virtual_now = 0.0
        self._ambiguity: dict[str, float] = {}
        self._urgent: set[str] = set()
        self._refresh: set[str] = set()  # sources whose waiting frame is a refresh of an unchanged view
        self._last_took_urgent = False
        self._lock = threading.Lock()

    def weight(self, source: str) -> float:
        settings = self.settings
        with self._lock:
            ambiguity = self._ambiguity.get(source, 0.0)
        motion = min(1.0, max(0.0, self.motion_of(source)))
        return settings.base_weight + motion * (settings.motion_weight + settings.ambiguity_weight * ambiguity)

    def choose(self, waiting: Sequence[Waiting], now: float) -> str:
        overdue = [w for w in waiting if now - w.since >= self.settings.max_wait_s]
        if overdue:
            return min(overdue, key=lambda w: w.since).source
        with self._lock:
            urgent = [w for w in waiting if w.source in self._urgent]
            others = [w for w in waiting if w.source not in self._urgent]
            urgent_turn = bool(urgent) and (not self._last_took_urgent or not others)
            news = [w for w in others if w.source not in self._refresh]
        if urgent_turn:
            return min(urgent, key=lambda w: w.since).source
        return min(news or others, key=lambda w: (self._turn(w.source)[1], w.since)).source

    def _turn(self, source: str) -> tuple[float, float]:
        """(start, finish) in virtual time of the source's next turn; its start is fixed when first asked."""
        weight = self.weight(source)
        with self._lock:
            start = self._start.get(source)
            if start is None:
                start = self._start[source] = max(self._virtual_now, self._finish.get(source, -math.inf))
        return start, start + 1.0 / weight

    def taken(self, source: str, now: float) -> None:
        start, finish = self._turn(source)
        with self._lock:
            del self._start[source]
            self._finish[source] = finish
            self._virtual_now = max(self._virtual_now, start)
            self._last_took_urgent = source in self._urgent
            self._urgent.discard(source)
            self._refresh.discard(source)
        self._log.add(source, now)

    def mark_urgent(self, source: str) -> None:
        with self._lock:
            self._urgent.add(source)
            self._refresh.discard(source)

    def mark_refresh(self, source: str, refresh: bool) -> None:
        """Whether the source's waiting frame only refreshes an unchanged view (set for each frame sent on)."""
        with self._lock:
            if refresh:
                self._refresh.add(source)
            else:
                self._refresh.discard(source)

    def set_ambiguity(self, source: str, ambiguity: float) -> None:
        with self._lock:
            self._ambiguity[source] = min(1.0, max(0.0, ambiguity))

    def shares(self) -> dict[str, Share]:
        measured = self._log.shares()
        with self._lock:
            known = set(self._finish) | set(self._ambiguity)
        return {
            source: Share(round(self.weight(source), 3), round(measured.get(source, 0.0), 3))
            for source in sorted(known | set(measured))
        }

    def forget(self, source: str) -> None:
        with self._lock:
            self._finish.pop(source, None)
            self._start.pop(source, None)
            self._ambiguity.pop(source, None)
            self._urgent.discard(source)
            self._refresh.discard(source)
        self._log.forget(source)


def policy_for(settings: ScheduleSettings, motion_of: Callable[[str], float] = lambda source: 0.0) -> SharePolicy:
    if settings.policy == "round_robin":
        return RoundRobin()
    return NeedShare(settings, motion_of)


def ambiguity_of(
    uncertainty: NDArray[np.floating], match: NDArray[np.floating] | None, settings: ScheduleSettings
) -> float:
    """The share of ambiguous or novel patches in the map's lower half: the ground ahead of a forward camera."""
    rows = uncertainty.shape[0]
    ahead = slice(rows // 2, rows)
    unclear = np.asarray(uncertainty[ahead]) >= settings.ambiguous_u
    if match is not None and settings.novel_match > 0:
        unclear |= np.asarray(match[ahead]) < settings.novel_match
    return float(unclear.mean()) if unclear.size else 0.0
