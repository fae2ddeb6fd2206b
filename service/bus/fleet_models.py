"""The model each instance runs, on the bus: advertise this one's, learn the others', refuse a stray model.

Each instance holds one liveliness token ``{prefix}/member/{instance}/{fingerprint}/{state}/{millis}``
(re-declared when its state changes) and watches everyone's, with history. ``service/runtime/fleet_models.py``
decides from them who takes no sources; ``Membership`` leaves those out of the assignment table.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable

import zenoh
from gcdtrav.schemas.keys import Keys
from gcdtrav.service.bus.entities import undeclare_all
from gcdtrav.service.runtime.fleet_models import (
    HELD,
    MIXED,
    FleetModelsStatus,
    FleetView,
    Member,
    decide,
    own_state,
)

log = logging.getLogger("gcdtrav.service")
HISTORY_TIMEOUT_S = 1.0  # the first look at the others' tokens, before this instance decides anything


class FleetModels:
    def __init__(self, session: zenoh.Session, keys: Keys, instance: str, fingerprint: str, allow_mixed: bool) -> None:
        self.session, self.keys, self.instance = session, keys, instance
        self.fingerprint, self.allow_mixed = fingerprint, allow_mixed
        self.on_change: Callable[[], None] | None = None  # set by Membership: re-decide with the live set
        self._lock = threading.Lock()
        self._members: dict[str, Member] = {}
        self._closed = False
        self._view = FleetView({}, None)
        self._token: zenoh.LivelinessToken | None = None
        self._declare(MIXED if allow_mixed else HELD)  # held until decided: see the runtime module
        for reply in session.liveliness().get(keys.member("**"), timeout=HISTORY_TIMEOUT_S):
            if reply.ok is not None:
                self._learn(str(reply.ok.key_expr), zenoh.SampleKind.PUT)
        self._subscriber = session.liveliness().declare_subscriber(keys.member("**"), self._on_token, history=True)

    def _declare(self, state: str) -> None:
        member = Member(self.instance, self.fingerprint, state, int(time.time() * 1000))
        key = self.keys.member(self.instance, self.fingerprint, state, member.since_ms)
        with self._lock:
            if self._closed:
                return
            old, self._token = self._token, self.session.liveliness().declare_token(key)
            self._members[self.instance] = member
        if old is not None:
            undeclare_all([old])

    def _learn(self, key: str, kind: zenoh.SampleKind) -> bool:
        """Keep the others' newest token; True when what is known changed."""
        parsed = self.keys.parse_member(key)
        if parsed is None or parsed[0] == self.instance:
            return False
        member = Member(*parsed)
        with self._lock:
            known = self._members.get(member.instance)
            if kind == zenoh.SampleKind.DELETE:
                if known != member:  # an older token of a re-declared state going away
                    return False
                del self._members[member.instance]
            elif known is not None and known.since_ms > member.since_ms:
                return False
            else:
                self._members[member.instance] = member
        return True

    def _on_token(self, sample: zenoh.Sample) -> None:
        if self._learn(str(sample.key_expr), sample.kind) and self.on_change is not None:
            self.on_change()

    def member(self, instance: str) -> Member | None:
        with self._lock:
            return self._members.get(instance)

    def settle(self, live: Iterable[str]) -> FleetView:
        """Decide for the live instances; advertise this one's new state; say so when it changes."""
        live = set(live)
        with self._lock:
            view = decide(live, dict(self._members))
            before, self._view = self._view, view
            current = self._members[self.instance].state
        # a withdrawn instance (not live) keeps its token as it is until it rejoins
        state = own_state(self.instance, view, self.allow_mixed) if self.instance in live else current
        if state != current:
            self._declare(state)
        why, was = view.refused.get(self.instance), before.refused.get(self.instance)
        if why and why != was:
            log.warning("this instance takes no sources: %s", why)
        elif was and not why:
            log.warning("this instance takes sources again: the fleet's model is its own (%s)", self.fingerprint)
        if view.suspended and view.suspended != before.suspended:
            log.warning("model check suspended: %s", view.suspended)
        return view

    def status(self, live: Iterable[str]) -> FleetModelsStatus:
        """Why this instance is refused ("" if not) and the fingerprint of every live instance advertising one."""
        with self._lock:
            fingerprints = {name: self._members[name].fingerprint for name in live if name in self._members}
            return FleetModelsStatus(self._view.refused.get(self.instance, ""), fingerprints)

    def close(self) -> None:
        with self._lock:
            self._closed = True
            token, self._token = self._token, None
        undeclare_all(entity for entity in (self._subscriber, token) if entity is not None)
