"""Which live instance serves which source: liveliness tokens in, ``service/runtime/fleet/assignment.py`` decides.

Every instance declares ``{prefix}/alive/{instance}`` and watches the others' tokens; each computes the same
bounded-load table from the live instances and the sources it sees on the inputs, with no coordinator.
An instance that stalls (``service/runtime/progress.py``) withdraws its token: the others take its sources
within their liveliness delay, and it serves nothing until it rejoins (declares the token again).
With ``models`` (``service/bus/fleet_models.py``), instances refused for their model stay out of the table.
Joins and leaves are logged as warnings, with the instance's model and anchor set: never silent.

Scaling robots do not feel: a starting instance watches the others and notes the sources before it joins
(``join=False``, then ``rejoin`` once it serves), so it takes sources only when it can serve them; a leaving
one withdraws its token first (``leave``) and finishes the frames already in its hands.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

import zenoh
from gcdtrav.schemas.keys import Keys
from gcdtrav.service.bus.entities import undeclare_all
from gcdtrav.service.bus.fleet_models import FleetModels
from gcdtrav.service.runtime.fleet.assignment import Assignment, owner_of, weight

log = logging.getLogger("gcdtrav.service")
__all__ = ["Membership", "owner_of", "weight"]


class Membership:
    """The live instances of one prefix, kept current by a liveliness subscriber."""

    def __init__(
        self,
        session: zenoh.Session,
        prefix: str,
        instance: str,
        on_change: Callable[[set[str]], None] | None = None,
        assignment: Assignment | None = None,
        models: FleetModels | None = None,
        anchor_set_of: Callable[[str], str | None] = lambda instance: None,
        join: bool = True,
    ) -> None:
        self.instance = instance
        self.models, self._anchor_set_of = models, anchor_set_of
        self.session = session
        self.assignment = assignment or Assignment()
        self._keys = Keys(prefix)
        self._others: set[str] = set()
        self._lock = threading.Lock()
        self._on_change = on_change
        self._token: zenoh.LivelinessToken | None = (
            session.liveliness().declare_token(self._keys.alive(instance)) if join else None
        )
        if models is not None:
            models.on_change = self._changed
        self.assignment.set_instances(self.serving())
        self._subscriber = session.liveliness().declare_subscriber(self._keys.alive("*"), self._on_sample, history=True)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        name = self._keys.instance_of(str(sample.key_expr))
        if name is None or name == self.instance:
            return
        with self._lock:
            before = set(self._others)
            if sample.kind == zenoh.SampleKind.DELETE:
                self._others.discard(name)
            elif sample.kind == zenoh.SampleKind.PUT:
                self._others.add(name)
            changed = self._others != before
        if changed:
            verb = "left" if sample.kind == zenoh.SampleKind.DELETE else "joined"
            log.warning("instance %s %s (%s); instances now %s", name, verb, self.describe(name), sorted(self.live()))
            self._changed()

    def describe(self, instance: str) -> str:
        """'model 3f2a... (serving), anchor set 1a2b...' as this instance knows them."""
        member = self.models.member(instance) if self.models is not None else None
        model = (
            f"model {member.fingerprint or 'without fingerprint'} ({member.state})"
            if member
            else "model not advertised"
        )
        return f"{model}, anchor set {self._anchor_set_of(instance) or 'not announced yet'}"

    def _changed(self) -> None:
        live = self.live()
        self.assignment.set_instances(self.serving(live))
        log.info("instances now %s", sorted(live))
        if self._on_change is not None:
            self._on_change(live)

    def serving(self, live: set[str] | None = None) -> set[str]:
        """The live instances that take sources: all of them, less those refused for their model."""
        live = self.live() if live is None else live
        return live if self.models is None else self.models.settle(live).eligible(live)

    @property
    def withdrawn(self) -> bool:
        with self._lock:
            return self._token is None

    def withdraw(self) -> None:
        """Leave the fleet: undeclare the token; this instance owns nothing until ``rejoin``."""
        with self._lock:
            token, self._token = self._token, None
        if token is not None:
            undeclare_all([token])
            self._changed()

    def leave(self) -> Callable[[str], bool]:
        """Leave the fleet for good (shutdown): the token goes first, so the others take the sources now.
        Returns whether this instance owned a source just before: the frames it already holds are finished."""
        if self.withdrawn:  # a stalled instance had left already: it owns nothing to finish
            return lambda source: False
        owner = self.assignment.frozen()
        self.withdraw()
        return lambda source: owner(source) == self.instance

    def rejoin(self) -> None:
        with self._lock:
            if self._token is not None:
                return
            self._token = self.session.liveliness().declare_token(self._keys.alive(self.instance))
        self._changed()

    def live(self) -> set[str]:
        """The instances serving now, this one unless withdrawn."""
        with self._lock:
            return self._others | ({self.instance} if self._token is not None else set())

    def note(self, source: str) -> None:
        """A frame of ``source`` on the inputs: it counts in the table once established."""
        self.assignment.note(source)

    def owner(self, source: str) -> str | None:
        return self.assignment.owner(source)

    def owns(self, source: str) -> bool:
        return not self.withdrawn and self.owner(source) == self.instance

    def owned(self) -> int:
        """The established sources the table gives this instance (none while withdrawn): across the live
        instances these counts sum to the fleet's established sources."""
        if self.withdrawn:
            return 0
        return sum(owner == self.instance for owner in self.assignment.table().values())

    def close(self) -> None:
        with self._lock:
            token, self._token = self._token, None
        undeclare_all(entity for entity in (self._subscriber, token) if entity is not None)
        if self.models is not None:
            self.models.close()
