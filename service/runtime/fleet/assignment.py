"""Which live instance serves which source: rendezvous weights with bounded loads. No middleware here.

Every instance computes the same table from what it sees by itself, with no coordinator: the live
instances (their liveliness tokens) and the sources on the inputs (every instance subscribes to every
input, so all see the same names). Each (instance, source) pair has a rendezvous weight (a hash); the
pairs are taken by weight, highest first, and a source goes to the first instance of its pairs that still
has room. Room: loads may differ by at most one (with n sources on k instances, n mod k instances take
ceil(n / k), the others floor(n / k)). Hashing alone split README's eight robots 6/2 on two boxes.

Only *established* sources (``established_after`` frames or more) enter the table, so a flood of one-frame
names never moves a robot; a source not (yet) in the table goes to its highest-weight instance. Sources
silent for ``idle_s`` leave it, and at most ``max_known`` names are remembered (beyond: highest weight).
The table changes only when the instances or the established sources change.
"""

from __future__ import annotations

import hashlib
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable

SWEEP_INTERVAL_S = 1.0
# How long a silent source stays in the table. Every instance's table must hold the same sources, and an instance
# that joins has seen only the sources that sent frames since it started: a source silent for minutes but still
# in the others' tables made them disagree, and a robot could be left to no instance until it left them (36 s in
# benchmarks/autoscale.py with source_idle_s, 300 s). Short, so that any disagreement ends within it; sources
# slower than one frame per TABLE_IDLE_S leave and re-enter the table (rebalancing the others).
TABLE_IDLE_S = 10.0


def weight(instance: str, source: str) -> int:
    digest = hashlib.sha256(f"{instance}\x00{source}".encode()).digest()
    return int.from_bytes(digest[:8], "big")


def owner_of(source: str, instances: Iterable[str]) -> str:
    """The highest-weight instance: the owner without a load bound."""
    return max(instances, key=lambda instance: (weight(instance, source), instance))


def assign(instances: Iterable[str], sources: Iterable[str]) -> dict[str, str]:
    """source -> instance, every load floor(n / k) or ceil(n / k); the same result for the same sets."""
    names, known = sorted(set(instances)), sorted(set(sources))
    if not names:
        return {}
    floor, extra = divmod(len(known), len(names))  # ``extra`` instances may take floor + 1
    pairs = sorted(((weight(i, s), i, s) for s in known for i in names), reverse=True)
    owner: dict[str, str] = {}
    load: Counter[str] = Counter()
    for _, instance, source in pairs:
        if source in owner or not _has_room(load[instance], floor, extra):
            continue
        owner[source] = instance
        load[instance] += 1
        if load[instance] == floor + 1:
            extra -= 1
    return owner


def _has_room(load: int, floor: int, extra: int) -> bool:
    return load < floor or (load == floor and extra > 0)


class Assignment:
    """The table for one instance's view; thread-safe (zenoh's callbacks note frames and membership)."""

    def __init__(
        self,
        established_after: int = 2,
        idle_s: float = 300.0,
        max_known: int = 1024,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.established_after, self.idle_s, self.max_known = established_after, idle_s, max_known
        self._clock = clock
        self._lock = threading.Lock()
        self._instances: frozenset[str] = frozenset()
        self._frames: dict[str, int] = {}
        self._last_seen: dict[str, float] = {}
        self._table: dict[str, str] = {}
        self._next_sweep = clock() + SWEEP_INTERVAL_S

    def set_instances(self, instances: Iterable[str]) -> None:
        with self._lock:
            if frozenset(instances) != self._instances:
                self._instances = frozenset(instances)
                self._rebuild()

    def note(self, source: str) -> None:
        """A frame of ``source`` on the inputs (any instance's, before ownership is decided)."""
        with self._lock:
            now = self._clock()
            self._sweep(now)
            if source not in self._frames and len(self._frames) >= self.max_known and not self._forget_a_newcomer():
                return
            count = self._frames.get(source, 0) + 1
            self._frames[source], self._last_seen[source] = count, now
            if count == self.established_after:
                self._rebuild()

    def owner(self, source: str) -> str | None:
        """The instance serving ``source``; None while no instance is live."""
        with self._lock:
            if not self._instances:
                return None
            return self._table.get(source) or owner_of(source, self._instances)

    def table(self) -> dict[str, str]:
        with self._lock:
            return dict(self._table)

    def frozen(self) -> Callable[[str], str | None]:
        """``owner`` as it answers now, unchanged by later changes (an instance leaving finishes with it)."""
        with self._lock:
            table, instances = dict(self._table), self._instances
        return lambda source: (table.get(source) or owner_of(source, instances)) if instances else None

    def _forget_a_newcomer(self) -> bool:
        """Room for a new name when full: the longest-known name with a single frame goes (a flood's)."""
        newcomer = next((source for source, count in self._frames.items() if count < self.established_after), None)
        if newcomer is None:
            return False
        del self._frames[newcomer], self._last_seen[newcomer]
        return True

    def _sweep(self, now: float) -> None:
        if now < self._next_sweep:
            return
        self._next_sweep = now + SWEEP_INTERVAL_S
        idle = [source for source, seen in self._last_seen.items() if now - seen > self.idle_s]
        for source in idle:
            del self._last_seen[source]
            self._frames.pop(source, None)
        if any(source in self._table for source in idle):
            self._rebuild()

    def _rebuild(self) -> None:
        established = [source for source, count in self._frames.items() if count >= self.established_after]
        self._table = assign(self._instances, established)
