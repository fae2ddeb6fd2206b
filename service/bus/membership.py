"""Which live instance serves which source: rendezvous (highest-random-weight) hashing over liveliness.

Every instance declares ``{prefix}/alive/{instance}`` and watches the others' tokens. A source belongs to
the live instance with the highest hash of (instance, source): every instance computes the same owner
from the same membership, with no coordinator, and when an instance joins or leaves only the sources it
gains or loses move.
"""

from __future__ import annotations

import hashlib
import logging
import threading
from collections.abc import Callable, Iterable

import zenoh
from gcdtrav.schemas.keys import Keys
from gcdtrav.service.bus.entities import undeclare_all

log = logging.getLogger("gcdtrav.service")


def weight(instance: str, source: str) -> int:
    digest = hashlib.sha256(f"{instance}\x00{source}".encode()).digest()
    return int.from_bytes(digest[:8], "big")


def owner_of(source: str, instances: Iterable[str]) -> str:
    return max(instances, key=lambda instance: (weight(instance, source), instance))


class Membership:
    """The live instances of one prefix, kept current by a liveliness subscriber."""

    def __init__(
        self, session: zenoh.Session, prefix: str, instance: str, on_change: Callable[[set[str]], None] | None = None
    ) -> None:
        self.instance = instance
        self._keys = Keys(prefix)
        self._live: set[str] = {instance}
        self._lock = threading.Lock()
        self._on_change = on_change
        self._token = session.liveliness().declare_token(self._keys.alive(instance))
        self._subscriber = session.liveliness().declare_subscriber(self._keys.alive("*"), self._on_sample, history=True)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        name = self._keys.instance_of(str(sample.key_expr))
        if name is None:
            return
        with self._lock:
            before = set(self._live)
            if sample.kind == zenoh.SampleKind.DELETE and name != self.instance:
                self._live.discard(name)
            elif sample.kind == zenoh.SampleKind.PUT:
                self._live.add(name)
            after = set(self._live)
        if after != before:
            log.info("instances now %s", sorted(after))
            if self._on_change is not None:
                self._on_change(after)

    def live(self) -> set[str]:
        with self._lock:
            return set(self._live)

    def owner(self, source: str) -> str:
        return owner_of(source, self.live())

    def owns(self, source: str) -> bool:
        return self.owner(source) == self.instance

    def close(self) -> None:
        undeclare_all((self._subscriber, self._token))
