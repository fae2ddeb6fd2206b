"""Our publishers say who they are: each input frame carries zenoh's source info (the publisher's session
id and a sequence number), so the service can cap the sources one publisher may create
(``max_sources_per_publisher``). Zenoh leaves ``sample.source_info`` None unless the publisher sets it.
It is a claim, not a proof: a hostile peer can omit or forge it, which is what deploy/access-control.json5
is for; it caps a well-meaning robot that invents names (a frame counter in the source)."""

from __future__ import annotations

import itertools
import threading

import zenoh

_sequence = itertools.count(1)
_lock = threading.Lock()


def put_identified(publisher: zenoh.Publisher, payload: bytes, encoding: zenoh.Encoding | None = None) -> None:
    """``publisher.put`` with the publisher's id and the next sequence number as the sample's source info."""
    with _lock:
        sn = next(_sequence)
    publisher.put(payload, encoding=encoding, source_info=zenoh.SourceInfo(publisher.id, sn))
