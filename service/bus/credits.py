"""Puts the credit ledger's grants (service/runtime/credits.py, ``Credits``) on ``{prefix}/credit/{source}``.

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
from gcdtrav.schemas.messages import MSGPACK_ENCODING, CreditGrant
from gcdtrav.service.bus.entities import undeclare_all

log = logging.getLogger("gcdtrav.service")


class CreditPublisher:
    """The runtime's ``CreditSink`` (service/runtime/credits.py): one express publisher per source."""

    def __init__(self, session: zenoh.Session, keys: Keys) -> None:
        self.session, self.keys = session, keys
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._lock = threading.Lock()
        self._closed = False

    def put(self, source: str, grant: CreditGrant) -> bool:
        with self._lock:
            if self._closed:
                return False
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
        return True

    def forget(self, source: str) -> None:
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
