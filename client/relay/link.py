"""What both robot sides of the relay share (the zenoh bus, client/relay/zenoh_side.py; the ROS 2 graph,
ros2_node.py): the outputs' keys and encodings, a zenoh entity two threads use safely (``Guarded``), and the one
on-demand forwarder (``OnDemand``): an output of one source brought over the link only while someone on the
robot's side wants it, every arrival heard by the mask's guard, a late mask never put in force."""

from __future__ import annotations

import contextlib
import logging
import math
import threading
from collections.abc import Callable
from typing import Any, Protocol

import zenoh
from gcdtrav.client.relay.mask_guard import SAFE
from gcdtrav.client.relay.state import RateWindow
from gcdtrav.schemas.keys import Keys
from gcdtrav.schemas.messages import MSGPACK_ENCODING, MessageError, peek_fields
from gcdtrav.schemas.relay import RelaySettings

log = logging.getLogger("gcdtrav.relay")
MSGPACK = zenoh.Encoding(MSGPACK_ENCODING)
STAMPED_OUTPUTS = ("maps", "maps8", "grid")  # their header's stamp is the capture stamp of the newest frame
# the grid's CDRs, under {prefix}/out/{source}/grid/ (service/runtime/grids/outputs.py)
GRID_CDRS = ("speed_mask", "speed_limit", "costmap", "nav2_costmap")
GUARDED = ("speed_mask", "speed_limit")  # what the mask's guard puts in force (client/relay/mask_guard.py)
OUTPUT_ENCODINGS = {
    "maps": MSGPACK,
    "maps8": MSGPACK,
    "grid": MSGPACK,
    "preview": zenoh.Encoding.IMAGE_JPEG,
    **dict.fromkeys(GRID_CDRS, zenoh.Encoding.APPLICATION_CDR),
}


def output_key(keys: Keys, source: str, kind: str) -> str:
    """Where the service publishes ``kind`` of ``source``: the grid's CDRs under its grid key."""
    return keys.grid(source, kind) if kind in GRID_CDRS else keys.output(source, kind)


def maps_stamp(payload: bytes) -> float | None:
    """The capture stamp in a maps' or grid's msgpack header; None when it has none."""
    try:
        header = peek_fields(payload, ("header",)).get("header")
        return float(header["stamp"]) if isinstance(header, dict) else None
    except (MessageError, KeyError, TypeError, ValueError):
        return None


class Undeclarable(Protocol):
    def undeclare(self) -> None: ...


class RelayView(Protocol):
    """What the robot sides and the forwarders use of the relay (client/relay/relay.py ``Relay``)."""

    link: zenoh.Session
    keys: Keys
    settings: RelaySettings
    guards: dict[str, Any]

    def heard(self, source: str) -> None: ...

    def observe_output(self, source: str, stamp: float) -> None: ...

    def mask_arrived(self, source: str, payload: bytes) -> bool: ...

    def robot_pose(self, x: float, y: float, frame_id: str) -> None: ...

    def wake(self) -> None: ...


class Guarded:
    """A zenoh entity that one thread uses while another may undeclare it (a zenoh callback's put, the relay's
    close). zenoh-python's entities are pyo3 objects: ``put`` borrows the publisher while zenoh works with the
    GIL released, ``undeclare`` borrows it mutably, and the two at once raise ``RuntimeError: Already
    borrowed``; zenoh's undeclare of a subscriber does not wait for its callbacks under way either. So every
    use and the undeclare take one lock, and after ``undeclare`` a use is skipped."""

    def __init__(self, entity: Any) -> None:
        self._entity = entity
        self._lock = threading.Lock()
        self._undeclared = False

    def use(self, action: Callable[[Any], object]) -> bool:
        """``action(entity)`` unless undeclared; False if skipped."""
        with self._lock:
            if self._undeclared:
                return False
            action(self._entity)
            return True

    def put(self, payload: Any, **options: Any) -> bool:
        """A publisher's ``put``, unless undeclared; False if skipped."""
        return self.use(lambda publisher: publisher.put(payload, **options))

    def matching(self) -> bool:
        """A publisher's: whether any subscriber anywhere matches its key now (False once undeclared)."""
        with self._lock:
            return not self._undeclared and bool(self._entity.matching_status.matching)

    def undeclare(self) -> None:
        with self._lock:
            if self._undeclared:
                return
            self._undeclared = True
            try:
                self._entity.undeclare()
            except zenoh.ZError as err:  # the session may be closing
                log.debug("undeclare failed: %s", err)


class OnDemand:
    """One output of one source, brought over the link only while someone on the robot's side wants it
    (``wanted``, set by the robot side). The link's subscriber is declared and undeclared by the relay's control
    thread (``reconcile``), never in a zenoh or rclpy callback. Every arrival is a sign of the service for the
    mask's guard; a speed mask the guard refuses (late) is not delivered. ``deliver`` puts it on the robot's
    side and returns the capture stamp it carries, if known."""

    wanted_by = "a consumer on the robot"

    def __init__(self, relay: RelayView, source: str, kind: str, key: str | None = None) -> None:
        self.relay, self.source, self.kind = relay, source, kind
        self.key = key or output_key(relay.keys, source, kind)
        self.downlink = RateWindow()
        self.wanted = False
        self._subscriber: Guarded | None = None

    @property
    def active(self) -> bool:
        return self._subscriber is not None

    def want(self, wanted: bool) -> bool:
        """Whether anyone on the robot's side wants the output now (the robot side says); True when that changed."""
        changed = wanted != self.wanted
        self.wanted = wanted
        return changed

    def reconcile(self) -> None:
        if self.wanted and self._subscriber is None:
            self._subscriber = Guarded(self.relay.link.declare_subscriber(self.key, self._arrived))
            log.info("forwarding %s: %s subscribes", self.key, self.wanted_by)
        elif not self.wanted and self._subscriber is not None:
            self._subscriber.undeclare()
            self._subscriber = None
            log.info("no longer forwarding %s: nobody on the robot subscribes", self.key)

    def _arrived(self, sample: zenoh.Sample) -> None:
        self.relay.heard(self.source)
        guard = self.relay.guards.get(self.source) if self.kind in GUARDED else None
        with guard.turn if guard is not None else contextlib.nullcontext():
            if self.kind == "speed_mask" and not self.relay.mask_arrived(self.source, sample.payload.to_bytes()):
                return  # late, or not a mask: the guard's safe mask stays (or comes) instead
            if self.kind == "speed_limit" and guard is not None and guard.state == SAFE:
                return  # the safe limit stays until a fresh mask is in force again
            stamp = self.deliver(sample)
        self.downlink.add(len(sample.payload))
        if stamp is not None and math.isfinite(stamp):
            self.relay.observe_output(self.source, stamp)

    def deliver(self, sample: zenoh.Sample) -> float | None:
        raise NotImplementedError

    def close(self) -> None:
        if self._subscriber is not None:
            self._subscriber.undeclare()
            self._subscriber = None
