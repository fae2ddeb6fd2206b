"""Which source's frame is inferred next (issue 34). No zenoh here; the queue asks, under its lock.

Every frame waiting for inference carries its claim (``Claim``), set by the glance (service/runtime/reuse.py)
or the queue: its class and its source's need at that glance. The classes:

- **first**: a source's first frame (nothing received from it before; the queue says);
- **urgent**: a changed view after reuse (its consumers hold maps of a view that is gone);
- **news**: any other frame that may show something new;
- **refresh**: an unchanged view inferred again because its maps are ``max_reuse_s`` old; it tells something
  new only if the change measure missed a change.

**One class at most every other turn** (``every_other_turn``, both policies): after a turn of a limited class,
the next goes to a frame of another class if one waits. First frames are limited, so a flood of new names (a
frame counter in the key, a hostile peer) gets at most half of the inference and the robots that keep
streaming the other half; the need policy limits urgent frames too, so views that keep flipping cannot starve
the rest. The rule comes before anything else, the floor included.

``RoundRobin``: the source waiting longest goes first: one frame per source in turn, whatever it shows.

``NeedShare``, a weighted fair share over the sources whose frames wait for inference. A source's weight is
``base_weight + motion * (motion_weight + ambiguity_weight * ambiguity)``, read from its frame's need:
motion (0..1) from its pose's speed, else from how fast its view changes; ambiguity (0..1), the share of
ambiguous (U >= ``ambiguous_u``) or novel (match < ``novel_match``) patches in the lower half of its last
map, the ground ahead of a forward camera. Ambiguity ahead counts as far as the robot moves towards it: a
parked robot's frames are refreshes of a view its maps already describe, and inferring them sooner tells
nobody anything new (measured: with ambiguity counted alone, random weights' ambiguous maps gave 4 parked
robots a third of a 2-core box, benchmarks/README.md). After the every-other-turn rule, in order:

1. **the floor**: a frame that has waited ``max_wait_s`` goes first (the longest waiting first); when every
   source is over it the rule is round-robin, the fairest there is for an overloaded box;
2. **an urgent frame** goes next (the longest waiting first);
3. otherwise weighted fair queueing (a virtual clock, as in stride scheduling): each turn a source takes
   costs it ``1 / weight`` of virtual time; the waiting source whose next turn would finish first
   (``max(virtual now, its last finish) + 1 / weight``) goes, and virtual now moves to that turn's start.
   Sources that always wait get turns in proportion to their weights; a source that was not waiting
   (parked, its views reused) comes back at virtual now, neither ahead (no credit banked while idle) nor
   behind. Each frame brings its source's need, so a robot that starts moving gets its share at its next
   frame. **Refreshes** yield: they go only when no other frame waits, or at the floor. Measured: 4 parked
   robots refreshing at the base weight took a tenth of a 2-core box from 4 moving ones
   (benchmarks/README.md, *A mixed fleet*).
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import Enum
from typing import Protocol

import numpy as np
from gcdtrav.schemas.settings.share import ScheduleSettings
from numpy.typing import NDArray

SHARE_WINDOW_S = 10.0


class FrameClass(str, Enum):
    FIRST = "first"
    URGENT = "urgent"
    NEWS = "news"
    REFRESH = "refresh"


@dataclass(frozen=True)
class Need:
    """What a source's frame is worth to the need policy, as known at its glance (both 0..1)."""

    motion: float = 0.0
    ambiguity: float = 0.0


NO_NEED = Need()


@dataclass(frozen=True)
class Claim:
    """A ready frame's claim on inference: its class and its source's need."""

    kind: FrameClass = FrameClass.NEWS
    need: Need = NO_NEED


NEWS_CLAIM = Claim()  # a frame nobody judged (no triage): news, at the base weight


@dataclass(frozen=True)
class Waiting:
    """A source with a frame ready for inference: since when it waits (its slot filled, monotonic), its claim."""

    source: str
    since: float
    claim: Claim = NEWS_CLAIM


@dataclass(frozen=True)
class Share:
    weight: float | None  # None: round-robin has no weights
    share: float  # of the inferences over the last SHARE_WINDOW_S


class SharePolicy(Protocol):
    name: str

    def choose(self, waiting: Sequence[Waiting], now: float) -> Waiting: ...

    def taken(self, chosen: Waiting, now: float) -> None: ...

    def shares(self) -> dict[str, Share]: ...

    def forget(self, source: str) -> None: ...


def every_other_turn(
    waiting: Sequence[Waiting], last: FrameClass | None, limited: frozenset[FrameClass]
) -> Sequence[Waiting]:
    """The frames that may go this turn: after a turn of a limited class, those of any other class (all if
    only that class waits)."""
    if last not in limited:
        return waiting
    return [w for w in waiting if w.claim.kind is not last] or waiting


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
    limited = frozenset({FrameClass.FIRST})  # it favours no class: only floods of new sources are limited

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._log = _TakeLog(clock)
        self._last: FrameClass | None = None

    def choose(self, waiting: Sequence[Waiting], now: float) -> Waiting:
        return min(every_other_turn(waiting, self._last, self.limited), key=lambda w: w.since)

    def taken(self, chosen: Waiting, now: float) -> None:
        self._last = chosen.claim.kind
        self._log.add(chosen.source, now)

    def shares(self) -> dict[str, Share]:
        return {source: Share(None, round(share, 3)) for source, share in self._log.shares().items()}

    def forget(self, source: str) -> None:
        self._log.forget(source)


class NeedShare:
    name = "need"
    limited = frozenset({FrameClass.FIRST, FrameClass.URGENT})

    def __init__(self, settings: ScheduleSettings, clock: Callable[[], float] = time.monotonic) -> None:
        self.settings = settings
        self._log = _TakeLog(clock)
        self._finish: dict[str, float] = {}  # virtual time each source's last turn finished
        self._start: dict[str, float] = {}  # virtual start of a waiting source's next turn, fixed when it began
        self._virtual_now = 0.0
        self._need: dict[str, Need] = {}  # each source's need as its last waiting frame told it (the status)
        self._last: FrameClass | None = None
        self._lock = threading.Lock()

    def weight(self, need: Need) -> float:
        settings = self.settings
        motion, ambiguity = (min(1.0, max(0.0, value)) for value in (need.motion, need.ambiguity))
        return settings.base_weight + motion * (settings.motion_weight + settings.ambiguity_weight * ambiguity)

    def choose(self, waiting: Sequence[Waiting], now: float) -> Waiting:
        with self._lock:
            self._need.update((w.source, w.claim.need) for w in waiting)
            waiting = every_other_turn(waiting, self._last, self.limited)
        overdue = [w for w in waiting if now - w.since >= self.settings.max_wait_s]
        if overdue:
            return min(overdue, key=lambda w: w.since)
        urgent = [w for w in waiting if w.claim.kind is FrameClass.URGENT]
        if urgent:
            return min(urgent, key=lambda w: w.since)
        news = [w for w in waiting if w.claim.kind is not FrameClass.REFRESH]
        return min(news or waiting, key=lambda w: (self._turn(w)[1], w.since))

    def _turn(self, waiting: Waiting) -> tuple[float, float]:
        """(start, finish) in virtual time of the source's next turn; its start is fixed when first asked."""
        weight = self.weight(waiting.claim.need)
        with self._lock:
            start = self._start.get(waiting.source)
            if start is None:
                start = max(self._virtual_now, self._finish.get(waiting.source, -math.inf))
                self._start[waiting.source] = start
        return start, start + 1.0 / weight

    def taken(self, chosen: Waiting, now: float) -> None:
        start, finish = self._turn(chosen)
        with self._lock:
            del self._start[chosen.source]
            self._finish[chosen.source] = finish
            self._virtual_now = max(self._virtual_now, start)
            self._last = chosen.claim.kind
        self._log.add(chosen.source, now)

    def shares(self) -> dict[str, Share]:
        measured = self._log.shares()
        with self._lock:
            known = set(self._finish) | set(measured)
            needs = {source: self._need.get(source, NO_NEED) for source in known}
        return {
            source: Share(round(self.weight(needs[source]), 3), round(measured.get(source, 0.0), 3))
            for source in sorted(known)
        }

    def forget(self, source: str) -> None:
        with self._lock:
            self._finish.pop(source, None)
            self._start.pop(source, None)
            self._need.pop(source, None)
        self._log.forget(source)


def policy_for(settings: ScheduleSettings) -> SharePolicy:
    if settings.policy == "round_robin":
        return RoundRobin()
    return NeedShare(settings)


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
