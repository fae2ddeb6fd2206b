"""The fleet's anchor set on the bus: announce this instance's active set, adopt a newer one announced.

Each instance holds one liveliness token ``{prefix}/active/{instance}/{millis}/{version}`` for its active
set (re-declared after every swap) and watches everyone's (with history: a new or rejoining instance sees
the current sets at once). When another instance announces a newer set (``service/runtime/fleet/fleet_anchors.py``
decides), this one installs it on the AnchorSwitch's worker: from the fleet's shared store, which recorded it
(one compare-and-swap transaction decided it); an instance with a store of its own fetches it from the
announcer's ``config/anchors/history`` reply and records it, keeping its accepted_at. The tokens only tell the
instances at once; the store is the record.
"""

from __future__ import annotations

import logging
import threading

import zenoh
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.keys import Keys
from gcdtrav.schemas.messages import AnchorHistoryEntry, AnchorHistoryReply, MessageError
from gcdtrav.service.bus.entities import undeclare_all
from gcdtrav.service.runtime.fleet.anchor_switch import AnchorSwitch
from gcdtrav.service.runtime.fleet.fleet_anchors import ActiveSet, FleetAnchors

log = logging.getLogger("gcdtrav.service")
FETCH_TIMEOUT_S = 5.0


class AnchorSync:
    def __init__(self, session: zenoh.Session, keys: Keys, instance: str, switch: AnchorSwitch) -> None:
        self.session, self.keys, self.instance, self.switch = session, keys, instance, switch
        self.fleet = FleetAnchors(instance)
        self._lock = threading.Lock()
        self._token: zenoh.LivelinessToken | None = None
        self._adopting: ActiveSet | None = None
        self._failed: ActiveSet | None = None  # not retried until something newer is announced
        self._closed = False
        self._announce(switch.head())
        switch.on_change(self._announce)
        self._subscriber = session.liveliness().declare_subscriber(
            keys.active_anchors("**"), self._on_token, history=True
        )

    def own(self) -> ActiveSet:
        head = self.switch.head()
        return ActiveSet.of(head.accepted_at, head.version)

    def _announce(self, head: AnchorHistoryEntry) -> None:
        active = ActiveSet.of(head.accepted_at, head.version)
        with self._lock:
            if self._closed:
                return
            old = self._token
            self._token = self.session.liveliness().declare_token(
                self.keys.active_anchors(self.instance, str(active.accepted_ms), active.version)
            )
        self.fleet.announced(self.instance, active)
        if old is not None:
            undeclare_all([old])

    def _on_token(self, sample: zenoh.Sample) -> None:
        parsed = self.keys.parse_active_anchors(str(sample.key_expr))
        if parsed is None:
            return
        instance, millis, version = parsed
        active = ActiveSet(millis, version)
        if sample.kind == zenoh.SampleKind.DELETE:
            if instance != self.instance:
                self.fleet.withdrawn(instance, active)
            return
        if instance != self.instance:
            self.fleet.announced(instance, active)
        self._adopt_newer()

    def _adopt_newer(self) -> None:
        target = self.fleet.to_adopt(self.own())
        with self._lock:
            if target is None or target[1] in (self._adopting, self._failed) or self._closed:
                return
            self._adopting = target[1]
        instance, active = target
        log.info(
            "instance %s announces anchor set %s (accepted at %d ms): adopting it",
            instance,
            active.version,
            active.accepted_ms,
        )
        self.switch.submit_adopt(active, lambda: self._fetch(instance, active), self._adopted)

    def _fetch(self, instance: str, active: ActiveSet) -> AnchorHistoryEntry | None:
        """The announced set's entry, from its instance's history reply (any instance holding it will do)."""
        replies = self.session.get(
            self.keys.anchor_history,
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=FETCH_TIMEOUT_S,
        )
        found: AnchorHistoryEntry | None = None
        for reply in replies:
            if reply.ok is None:
                continue
            try:
                history = AnchorHistoryReply.unpack(reply.ok.payload.to_bytes())
            except MessageError:
                continue
            for entry in history.entries:
                if entry.version == active.version and (found is None or history.instance == instance):
                    found = entry.model_copy(update={"accepted_at": active.accepted_ms / 1000})
        return found

    def _adopted(self, anchors: AnchorSet | None, error: BaseException | None) -> None:
        with self._lock:
            self._failed = self._adopting if error is not None else None
            self._adopting = None
        if error is not None:
            log.error("could not adopt the fleet's anchor set: %s", error)
        elif anchors is not None:
            log.info("anchor set %s adopted from the fleet", anchors.version)
        self._adopt_newer()  # a newer one may have been announced meanwhile

    def close(self) -> None:
        with self._lock:
            self._closed = True
            token, self._token = self._token, None
        undeclare_all(entity for entity in (self._subscriber, token) if entity is not None)
