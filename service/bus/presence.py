"""The relays' health over the link (``{prefix}/relay/{source}/health``): the robots heard, and whether they
parked a camera, for the silent-robot alert (runtime/intake/presence.py). Only wiring."""

from __future__ import annotations

import zenoh
from gcdtrav.schemas.keys import Keys
from gcdtrav.schemas.messages import MessageError, RelayHealth
from gcdtrav.service.runtime.intake.presence import SourcePresence
from gcdtrav.service.runtime.stats import ServiceStats

MAX_RELAY_HEALTH_BYTES = 64_000  # a health with every cause's sentence is under 2 kB


def declare_relay_health(
    session: zenoh.Session, keys: Keys, presence: SourcePresence, stats: ServiceStats
) -> zenoh.Subscriber:
    """Hear every relay's health; a bad one is counted (``bad_relay_health``) and changes nothing."""

    def on_health(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        source = keys.relay_health_source_of(key)
        if source is None:
            return
        try:
            health = RelayHealth.unpack(sample.payload.to_bytes(), max_bytes=MAX_RELAY_HEALTH_BYTES)
        except MessageError as err:
            stats.rejected(None, "bad_relay_health", f"{key}: {err}"[:200])
            return
        if health.source != source:
            stats.rejected(None, "bad_relay_health", f"{key}: the health names source '{health.source[:100]}'")
            return
        presence.relay_health(source, health.parked)

    return session.declare_subscriber(keys.relay_health("**"), on_health)
