"""The relay's robot side on the robot's zenoh bus (its own router: rmw_zenoh, zenoh-bridge-ros2dds, or plain
keys of images): cameras in, the service's outputs out on demand (``OutputForwarder``), the relay's health and
safe speed mask, the robot's pose and the inputs of its outcomes. The ROS 2 graph's counterpart: ros2_node.py."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from functools import partial
from typing import Protocol

import zenoh
from gcdtrav.client.relay.link import (
    MSGPACK,
    OUTPUT_ENCODINGS,
    STAMPED_OUTPUTS,
    Guarded,
    OnDemand,
    RelayView,
    maps_stamp,
)
from gcdtrav.client.relay.mask_guard import SafeMask
from gcdtrav.client.relay.outcomes import INPUT_ERRORS, OutcomeLink, robot_key
from gcdtrav.client.relay.ros_camera import ros_camera_key
from gcdtrav.schemas.experience import PlannedPath, TraversalOutcome
from gcdtrav.schemas.messages import MessageError, Pose2D, RelayHealth
from gcdtrav.schemas.outcomes import decode_command, decode_contact, decode_odometry
from gcdtrav.schemas.relay import FORWARDABLE, RelayCamera
from gcdtrav.schemas.ros_nav import odometry_pose, path_points, split_stamp

log = logging.getLogger("gcdtrav.relay")


class CameraFeed(Protocol):
    """What the robot side uses of a camera's link (client/relay/relay.py ``CameraLink``)."""

    source: str

    @property
    def relay(self) -> RelayView: ...

    @property
    def camera_key(self) -> str: ...

    def on_frame(self, sample: zenoh.Sample) -> None: ...

    def on_parked(self, sample: zenoh.Sample) -> None: ...


class OutputForwarder(OnDemand):
    """One output of one source onto the robot's bus, brought over the link only while a consumer there
    subscribes (zenoh's matching status of the robot-side publisher)."""

    def __init__(self, relay: RelayView, local: zenoh.Session, source: str, kind: str) -> None:
        super().__init__(relay, source, kind)
        publisher = local.declare_publisher(
            self.key, encoding=OUTPUT_ENCODINGS[kind], congestion_control=zenoh.CongestionControl.DROP
        )
        self._listener = Guarded(publisher.declare_matching_listener(self._on_matching))
        self._publisher = Guarded(publisher)  # zenoh's callbacks put on it while close() may undeclare it

    def _on_matching(self, status: zenoh.MatchingStatus) -> None:
        self.want(status.matching)
        self.relay.wake()  # (un)declared on the relay's thread, not in zenoh's callback

    def deliver(self, sample: zenoh.Sample) -> float | None:
        if not self._publisher.put(sample.payload, encoding=sample.encoding):
            return None  # a callback under way when the relay closed
        return maps_stamp(sample.payload.to_bytes()) if self.kind in STAMPED_OUTPUTS else None

    def put_local(self, payload: bytes) -> None:
        """On the robot's bus only (the relay's safe mask)."""
        self._publisher.put(payload, encoding=OUTPUT_ENCODINGS[self.kind])

    def close(self) -> None:
        super().close()
        self._listener.undeclare()
        self._publisher.undeclare()


class ZenohRobotSide:
    """The robot's zenoh bus (its own router: rmw_zenoh, zenoh-bridge-ros2dds, or plain keys of images)."""

    def __init__(self, local: zenoh.Session) -> None:
        self.local = local
        self._health: dict[str, Guarded] = {}
        self._masks: dict[str, OutputForwarder] = {}  # the speed mask's, where the safe mask goes too
        self._pose: Guarded | None = None
        self._bad_poses = 0

    def camera_name(self, camera: RelayCamera) -> str:
        if not camera.is_ros:
            return camera.camera
        return ros_camera_key(camera.camera, camera.ros_layout, camera.ros_domain, camera.zenoh_namespace)

    def subscribe_camera(self, link: CameraFeed) -> list[Guarded]:
        """The camera's frames, and the robot's word that it parked the camera (``CameraParked``)."""
        parked = link.relay.keys.relay_parked(link.source)
        return [
            Guarded(self.local.declare_subscriber(link.camera_key, link.on_frame)),
            Guarded(self.local.declare_subscriber(parked, link.on_parked)),
        ]

    def outputs(self, relay: RelayView, source: str) -> list[OnDemand]:
        key = relay.keys.relay_health(source)
        self._health[source] = Guarded(self.local.declare_publisher(key, encoding=MSGPACK))
        kinds = set(relay.settings.forward) | ({"speed_mask"} if relay.guards.get(source) else set())
        forwarders = [OutputForwarder(relay, self.local, source, kind) for kind in FORWARDABLE if kind in kinds]
        self._masks.update({f.source: f for f in forwarders if f.kind == "speed_mask"})
        if relay.settings.pose_key is not None and self._pose is None:
            handler = partial(self._on_pose, relay)
            self._pose = Guarded(self.local.declare_subscriber(relay.settings.pose_key, handler))
        return list(forwarders)

    def _on_pose(self, relay: RelayView, sample: zenoh.Sample) -> None:
        """The robot's pose on its bus: Pose2D msgpack, or an Odometry's CDR (rmw_zenoh)."""
        payload = sample.payload.to_bytes()
        try:
            # a CDR encapsulation header starts with a zero byte; msgpack maps start otherwise
            pose = odometry_pose(payload) if payload[:1] == b"\x00" else Pose2D.unpack(payload, max_bytes=4096)
        except MessageError as err:
            if self._bad_poses == 0:
                log.warning("pose on %s not usable (counted, said once): %s", sample.key_expr, err)
            self._bad_poses += 1
            return
        relay.robot_pose(pose.x, pose.y, pose.frame_id)

    def publish_health(self, health: RelayHealth) -> None:
        self._health[health.source].put(health.pack())

    def subscribe_outcomes(self, outcomes: OutcomeLink) -> list[Guarded]:
        """The robot's inputs of its outcomes on its bus: each a plain key (msgpack or JSON) or a ROS topic's
        rmw_zenoh keys (CDR)."""
        settings = outcomes.settings
        kind = "cmd_vel_stamped" if settings.cmd_vel_stamped else "cmd_vel"
        handlers: list[tuple[str | None, str, Callable[[bytes], None]]] = [
            (settings.cmd_vel, kind, lambda p: outcomes.on_command(decode_command(p, settings.cmd_vel_stamped))),
            (settings.odometry, "odometry", lambda p: outcomes.on_odometry(decode_odometry(p))),
            (settings.contact, "contact", lambda p: outcomes.on_contact(decode_contact(p))),
            (settings.outcome, "outcome", lambda p: outcomes.on_outcome(TraversalOutcome.decode(p, 4096))),
            (settings.planned_path, "planned_path", partial(_path_into, outcomes)),
        ]
        return [
            Guarded(self.local.declare_subscriber(robot_key(name, kind), partial(_decoded, outcomes, handle)))
            for name, kind, handle in handlers
            if name is not None
        ]

    def publish_safe_mask(self, mask: SafeMask) -> None:
        forwarder = self._masks.get(mask.source)
        if forwarder is not None:
            forwarder.put_local(mask.cdr(split_stamp(time.time())))  # stamped now, this host's clock

    def close(self) -> None:
        for publisher in [*self._health.values(), *([self._pose] if self._pose else [])]:
            publisher.undeclare()
        self._health.clear()


def _decoded(outcomes: OutcomeLink, handle: Callable[[bytes], None], sample: zenoh.Sample) -> None:
    """An input of the outcomes, decoded and handed over; a bad one counted, said once."""
    try:
        handle(sample.payload.to_bytes())
    except INPUT_ERRORS as err:
        if outcomes.rejected == 0:
            log.warning("%s not usable for outcomes (counted, said once): %s", sample.key_expr, err)
        outcomes.rejected += 1


def _path_into(outcomes: OutcomeLink, payload: bytes) -> None:
    """A nav_msgs/Path over rmw_zenoh (CDR: its first byte is zero) or a PlannedPath (msgpack or JSON)."""
    if payload[:1] == b"\x00":
        outcomes.on_path(*path_points(payload))
        return
    path = PlannedPath.decode(payload, 256 * 1024)
    outcomes.on_path(path.frame_id, path.stamp, [(float(x), float(y)) for x, y in path.points])
