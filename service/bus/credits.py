"""Puts the credit ledger's grants (service/runtime/credits.py) on ``{prefix}/credit/{source}``.

A grant is tiny and worth more than a map: it goes with priority INTERACTIVE_HIGH, ahead of the maps waiting
in the same link's queue, and express (not batched). It is published whether or not a relay listens: a
subscriber-less put costs a routing lookup. Only the source's owner grants, because only it takes the
source's frames (service/bus/membership.py).
"""

from __future__ import annotations

import logging
import threading

import zenoh
from gcdtrav.schemas.keys import Keys
from gcdtrav.schemas.messages import MSGPACK_ENCODING
from gcdtrav.service.bus.entities import undeclare_all
from gcdtrav.service.runtime.credits import TAKEN, CreditLedger, FrameTimes
from gcdtrav.service.runtime.frames import PendingFrame
from gcdtrav.service.runtime.stats import ServiceStats

log = logging.getLogger("gcdtrav.service")


class CreditPublisher:
    def __init__(self, session: zenoh.Session, keys: Keys, ledger: CreditLedger, stats: ServiceStats) -> None:
        self.session, self.keys, self.ledger, self.stats = session, keys, ledger, stats
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._lock = threading.Lock()
        self._closed = False

    def freed(self, source: str, reason: str, times: FrameTimes | None) -> None:
        """The source's slot is free (called from subscriber callbacks and the worker)."""
        grant = self.ledger.freed(source, reason, times, self.stats.problem(source))
        with self._lock:
            if self._closed:
                return
            publisher = self._publishers.get(source)
            if publisher is None:
                publisher = self.session.declare_publisher(
                    self.keys.credit(source),
                    encoding=zenoh.Encoding(MSGPACK_ENCODING),
                    congestion_control=zenoh.CongestionControl.DROP,
                    priority=zenoh.Priority.INTERACTIVE_HIGH,
                    express=True,
                )
                self._publishers[source] = publisher
            publisher.put(grant.pack())
        self.stats.credit(source)

    def taken(self, pending: PendingFrame) -> None:
        self.freed(pending.source, TAKEN, FrameTimes(pending.stamp, pending.sent_at, pending.received_at))

    def answered(self, pending: PendingFrame, reason: str) -> None:
        """The frame freed its slot without being taken: answered with the last maps (``unchanged``), or
        waiting for its refresh (``refresh``)."""
        self.freed(pending.source, reason, FrameTimes(pending.stamp, pending.sent_at, pending.received_at))

    def forget(self, source: str) -> None:
        self.ledger.forget(source)
        with self._lock:
            publisher = self._publishers.pop(source, None)
        if publisher is not None:
            undeclare_all([publisher])

    def close(self) -> None:
        with self._lock:
            self._closed = True
            publishers = list(self._publishers.values())
            self._publishers.clear()
        undeclare_all(publishers)
