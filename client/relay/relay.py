"""`gcdtrav relay`: the robot's side of a slow link (Wi-Fi, LTE) to the service. Torch-free.

Two zenoh sessions, so that nothing crosses the link unless the relay sends it:

- the **robot session** (``local_*`` settings; default: a client of the robot's own router, 127.0.0.1:7447)
  takes the cameras (zenoh keys of JPEG/PNG/ImageEnvelope, or ROS 2 Image/CompressedImage topics) and gives
  the robot's consumers the service's outputs;
- the **link session** (the zenoh flags) reaches the service.

Per camera, the newest frame waits in a slot; it goes out only with a credit: the service instance that owns
the source grants one on ``{prefix}/credit/{source}`` when the source's slot frees, so at most one frame of
the camera is inferred and one waits at the service. Before sending, the frame is shrunk to what the model
uses (the credit announces the model's input) and sent as a JPEG ImageEnvelope. A lost credit costs one
timeout (``credit_timeout_s``). Outputs (maps, maps8, grid, preview) cross the link only while a consumer on
the robot's bus subscribes to them. Every ``health_period_s`` the relay publishes a RelayHealth per camera on
the robot's bus (``{prefix}/relay/{source}/health``) with what may keep its maps stale (``causes.py``: a
silent camera, no instance answering, the service refusing, an unusable frame, a camera clock off this host's),
and logs each change once: stale, fresh again, a cause found or gone. The same health goes over the link every
``link_health_period_s`` (and at once when a camera is parked or runs again): the service's silent-robot alert
hears the robot through it. The robot's own software parks a camera it stops on purpose (``CameraParked`` on
``{prefix}/relay/{source}/parked``): its silence is then no cause and pages nobody.
Maps' ages are judged on this host's clock from the camera's stamps plus the camera's learnt clock offset
(``state.CameraClock``), as the service judges frames by delay: a camera stamping from another clock is
not stale forever.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any, Protocol

import zenoh
from gcdtrav.client.freshness import FreshnessWatch, Staleness
from gcdtrav.client.relay.causes import CameraFacts, causes, change_key
from gcdtrav.client.relay.link import MSGPACK, Guarded, OnDemand, Undeclarable
from gcdtrav.client.relay.mask_guard import SAFE, MaskGuard, SafeMask
from gcdtrav.client.relay.outcomes import OutcomeLink
from gcdtrav.client.relay.ros_camera import ros_type_of_key
from gcdtrav.client.relay.state import CameraClock, ClockEstimate, CreditWindow, RateWindow, downsized
from gcdtrav.client.relay.zenoh_side import ZenohRobotSide
from gcdtrav.client.session.source_info import put_identified
from gcdtrav.schemas.images import encode_jpeg
from gcdtrav.schemas.inputs import RejectedInput, decode_payload
from gcdtrav.schemas.keys import Keys, input_key
from gcdtrav.schemas.messages import CameraParked, CreditGrant, ImageEnvelope, MessageError, PixelEncoding, RelayHealth
from gcdtrav.schemas.relay import CLIPSEG_INPUT_SIDE, RelayCamera, RelayOutcomes, RelaySettings
from gcdtrav.schemas.ros_image import decode_ros_image
from gcdtrav.schemas.ros_nav import RosNavError, occupancy_grid_geometry, split_stamp

log = logging.getLogger("gcdtrav.relay")
MAX_CAMERA_PIXELS = 40_000_000
GUARD_PERIOD_S = 0.1  # how often the speed masks' guards are asked (client/relay/mask_guard.py)


STAMPS_KEPT = 64  # exact ROS stamps of the frames last sent, to stamp the outputs that come back


@dataclass(frozen=True)
class CapturedFrame:
    payload: zenoh.ZBytes | bytes  # kept as zenoh gave it: only the frames sent are copied and decoded
    encoding: str
    key: str
    arrived_at: float
    ros_type: str | None = None  # a message of the robot's ROS graph (the ROS 2 node): its type


class RobotSide(Protocol):
    """Where the cameras are and the outputs go: the robot's zenoh bus (``ZenohRobotSide``), or its ROS 2 graph
    through rclpy (client/relay/ros2_node.py)."""

    def camera_name(self, camera: RelayCamera) -> str:
        """The camera's key or topic, as the health names it."""
        ...

    def subscribe_camera(self, link: CameraLink) -> Iterable[Undeclarable]:
        """Feed ``link.keep`` with the camera's frames."""
        ...

    def outputs(self, relay: Relay, source: str) -> Sequence[OnDemand]: ...

    def publish_health(self, health: RelayHealth) -> None: ...

    def publish_safe_mask(self, mask: SafeMask) -> None:
        """Put the relay's safe speed mask where the live one goes (client/relay/mask_guard.py)."""
        ...

    def subscribe_outcomes(self, outcomes: OutcomeLink) -> Iterable[Undeclarable]:
        """Feed ``outcomes`` with the robot's commands, odometry, contacts, own outcomes and planned path."""
        ...

    def close(self) -> None: ...


def mask_age_s(link: CameraLink, stamp: float) -> float | None:
    """How long ago (this host's clock) the frame a mask was made of was captured; None before the camera's clock
    is learnt (a relay that sent no frame: it cannot tell)."""
    if link.camera_clock.offset_s() is None:
        return None
    return time.time() - link.camera_clock.on_host_clock(stamp)


class CameraLink:
    """One camera, one source: the newest frame, the credit, the sending thread."""

    def __init__(self, relay: Relay, camera: RelayCamera) -> None:
        self.relay, self.camera, self.source = relay, camera, camera.source
        self.window = CreditWindow(relay.settings.credit_timeout_s)
        self.clock = ClockEstimate()
        self.camera_clock = CameraClock()  # this host's clock minus the camera's
        self.last_frame_at: float | None = None  # this host's clock
        self.uplink = RateWindow()
        self.model_input = (CLIPSEG_INPUT_SIDE, CLIPSEG_INPUT_SIDE)
        self.captured = self.sent = self.undecodable = 0
        self.unusable: str | None = None  # why the last camera frame could not be sent, if it could not
        self.graph_causes: dict[str, str] = {}  # what the robot's ROS graph says is wrong (the ROS 2 node)
        self._ros_stamps: OrderedDict[float, tuple[int, int]] = OrderedDict()  # sent stamp -> (sec, nanosec)
        self.parked = False  # the robot's software stopped the camera on purpose (CameraParked)
        self._slot: CapturedFrame | None = None
        self._cond = threading.Condition()
        self._publisher: Guarded | None = None
        self._thread = threading.Thread(target=self._run, name=f"gcdtrav-relay-{self.source}", daemon=True)

    def start(self) -> list[Undeclarable]:
        """Declare the camera subscriber (robot), the credit subscriber and frame publisher (link); a camera whose
        frames reach the service another way (``frames: false``) only listens for credits."""
        credits = Guarded(self.relay.link.declare_subscriber(self.relay.keys.credit(self.source), self.on_grant))
        if not self.camera.frames:
            return [credits]
        frames_key = input_key(self.relay.settings.input_prefix, self.source)
        self._publisher = Guarded(self.relay.link.declare_publisher(frames_key, encoding=MSGPACK))
        declared = [*self.relay.robot.subscribe_camera(self), credits, self._publisher]
        self._thread.start()
        return declared

    @property
    def camera_key(self) -> str:
        return self.relay.robot.camera_name(self.camera)

    # ---- zenoh callbacks: keep, never decode ----------------------------------------------------------
    def on_frame(self, sample: zenoh.Sample) -> None:
        self.keep(CapturedFrame(sample.payload, str(sample.encoding), str(sample.key_expr), time.time()))

    def keep(self, frame: CapturedFrame) -> None:
        """The camera's newest frame: it replaces one not sent yet."""
        with self._cond:
            self._slot = frame  # an older frame not yet sent is replaced: only the newest matters
            self.captured += 1
            self.last_frame_at = frame.arrived_at
            self._cond.notify()

    def on_grant(self, sample: zenoh.Sample) -> None:
        arrived_at = time.time()
        try:
            grant = CreditGrant.unpack(sample.payload.to_bytes())
        except MessageError as err:
            log.warning("%s: ignoring a credit: %s", self.source, err)
            return
        self.clock.add(grant, arrived_at)
        self.relay.heard(self.source)
        self.relay.grant_seen(self.source, grant)
        self.relay.freshness.note_reason(self.source, grant.problem)
        with self._cond:
            self.model_input = grant.model_input
            self.window.grant(grant)
            self._cond.notify()

    def on_parked(self, sample: zenoh.Sample) -> None:
        """``CameraParked`` on ``{prefix}/relay/{source}/parked`` of the robot's bus (msgpack or JSON)."""
        try:
            notice = CameraParked.decode(sample.payload.to_bytes(), max_bytes=4096)
        except MessageError as err:
            log.warning("%s: ignoring a parked notice: %s", self.source, err)
            return
        self.park(notice)

    def park(self, notice: CameraParked) -> None:
        """The robot stops the camera on purpose (or runs it again): said in the health, over the link at once."""
        if notice.parked != self.parked:
            self.parked = notice.parked
            said = f" ({notice.reason})" if notice.reason else ""
            log.info("%s: camera %s%s", self.source, "parked" if notice.parked else "runs again", said)
            self.relay.tell_link_now()

    # ---- sending --------------------------------------------------------------------------------------
    def _run(self) -> None:
        while True:
            with self._cond:
                while not self.relay.stopping and not (self._slot is not None and self.window.ready()):
                    self._cond.wait(self.window.wait_s() or None)
                if self.relay.stopping:
                    return
                frame, self._slot = self._slot, None
                model_input = self.model_input
            assert frame is not None
            envelope = self._envelope(frame, model_input)
            if envelope is None:
                continue
            payload = envelope.pack()
            with self._cond:
                self.window.spend()
                self.sent += 1
            assert self._publisher is not None
            try:
                self._publisher.use(partial(put_identified, payload=payload))
            except zenoh.ZError as err:  # the session is closing
                log.debug("%s: send failed: %s", self.source, err)
            self.uplink.add(len(payload))

    def _envelope(self, frame: CapturedFrame, model_input: tuple[int, int]) -> ImageEnvelope | None:
        """The frame decoded, shrunk to what the model uses and JPEG-encoded; None (counted) when unusable."""
        try:
            image, stamp, frame_id, original_size = self._decode(frame)
        except RejectedInput as err:
            self.undecodable += 1
            self.unusable = f"camera frame on {frame.key} not usable: {err}"  # a cause: logged once per change
            return None
        self.unusable = None
        self.camera_clock.add(stamp, frame.arrived_at)
        settings = self.relay.settings
        small = downsized(image, settings.max_side, model_input)
        height, width = small.shape[:2]
        return ImageEnvelope(
            stamp=stamp,
            frame_id=frame_id,
            encoding=PixelEncoding.JPEG,
            width=width,
            height=height,
            data=encode_jpeg(small, settings.jpeg_quality),
            sent_at=time.time(),
            original_size=original_size,  # answers and maps in the camera's pixels, not the shrunk frame's
        )

    def _decode(self, frame: CapturedFrame) -> tuple[Any, float, str, tuple[int, int]]:
        """The camera's image, stamp, frame id and size in the camera's pixels."""
        payload = frame.payload if isinstance(frame.payload, bytes) else frame.payload.to_bytes()
        limit = self.relay.settings.max_camera_bytes
        if len(payload) > limit:
            raise RejectedInput("too_large", f"{len(payload)} bytes, over max_camera_bytes = {limit}")
        if frame.ros_type is None and not self.camera.is_ros:
            decoded = decode_payload(payload, frame.encoding, frame.arrived_at, limit, MAX_CAMERA_PIXELS)
            return decoded.image, decoded.stamp, decoded.frame_id, decoded.camera_size
        configured = self.camera.ros_message_type
        msgtype = frame.ros_type or ((ros_type_of_key(frame.key) or "") if configured == "auto" else configured)
        ros = decode_ros_image(payload, msgtype, MAX_CAMERA_PIXELS)
        self._remember_stamp(ros.stamp, (ros.sec, ros.nanosec))
        return ros.image, ros.stamp, ros.frame_id, (int(ros.image.shape[1]), int(ros.image.shape[0]))

    def _remember_stamp(self, stamp: float, exact: tuple[int, int]) -> None:
        with self._cond:
            self._ros_stamps[stamp] = exact
            while len(self._ros_stamps) > STAMPS_KEPT:
                self._ros_stamps.popitem(last=False)

    def ros_stamp(self, stamp: float) -> tuple[int, int]:
        """The exact (sec, nanosec) of the sent frame stamped ``stamp`` (a float's 0.2 us steps lose them): the
        stamp the robot's consumers match outputs to frames by. The frame's within 1 us, else ``stamp`` split."""
        with self._cond:
            near = min(self._ros_stamps, key=lambda sent: abs(sent - stamp), default=None)
            if near is not None and abs(near - stamp) < 1e-6:
                return self._ros_stamps[near]
        return split_stamp(stamp)

    def stop(self) -> None:
        with self._cond:
            self._cond.notify_all()
        if self._thread.is_alive():
            self._thread.join(5)

    def facts(self, now: float, refusal: str | None) -> CameraFacts:
        silent_since = self.last_frame_at if self.last_frame_at is not None else self.relay.started_at
        return CameraFacts(
            self.camera_key,
            now - silent_since if self.camera.frames else 0.0,  # frames: false: no camera to hear
            self.captured,
            self.window.unanswered,
            refusal,
            self.unusable,
            self.camera_clock.offset_s(),
            self.parked,
        )

    def health(self, freshness: FreshnessWatch, downlink: float, stale_after_s: float) -> RelayHealth:
        now = time.time()
        newest = freshness.newest(self.source)
        best = self.clock.best()
        settings = self.relay.settings
        found = causes(self.facts(now, freshness.reason(self.source)), settings.camera_silent_after_s, settings.prefix)
        found |= self.graph_causes
        return RelayHealth(
            source=self.source,
            published_at=now,
            newest_map_stamp=newest,
            map_age_s=None if newest is None else now - newest,
            stale=freshness.is_stale(self.source),
            stale_after_s=stale_after_s,
            frames_captured=self.captured,
            frames_sent=self.sent,
            credit_timeouts=self.window.timeouts,
            uplink_bytes_per_s=self.uplink.per_s() + self.relay.outcome_uplink(self.source),
            downlink_bytes_per_s=downlink,
            owner=self.window.owner,
            clock_offset_s=None if best is None else best[1],
            round_trip_s=None if best is None else best[0],
            problem=self.unusable or freshness.reason(self.source),
            causes=found,
            parked=self.parked,
            safe_mask=self.relay.safe_mask_reason(self.source),
        )


class Relay:
    """Every camera of one robot; ``start()``, then ``close()``. The sessions stay the caller's. The robot's side
    is its zenoh bus (``local``), or ``robot``: its ROS 2 graph (client/relay/ros2_node.py)."""

    def __init__(
        self,
        settings: RelaySettings,
        link: zenoh.Session,
        local: zenoh.Session | None = None,
        on_stale: Callable[[Staleness], None] | None = None,
        robot: RobotSide | None = None,
    ) -> None:
        if robot is None:
            if local is None:
                raise ValueError("a relay needs the robot's zenoh session or another robot side")
            robot = ZenohRobotSide(local)
        self.settings, self.link, self.robot = settings, link, robot
        self.keys = Keys(settings.prefix)
        self.freshness = FreshnessWatch(settings.stale_after_s)
        self.guards = {
            camera.source: MaskGuard(camera.source, settings.safe_mask_of(camera))
            for camera in settings.cameras
            if settings.safe_mask_of(camera).enabled
        }
        self.cameras = [CameraLink(self, camera) for camera in settings.cameras]
        self.outcomes: OutcomeLink | None = None  # outcomes measured here (settings.outcomes), from start()
        self.forwarders: list[OnDemand] = []
        self.stopping = False
        self._on_stale = on_stale
        self._declared: list[Undeclarable] = []
        self._link_health: dict[str, Guarded] = {}  # the same health over the link: the service hears the robot
        self._link_due = threading.Event()  # a camera parked or runs again: tell the service at once
        self._wake = threading.Event()
        self.started_at = time.time()
        self._told_causes: dict[str, dict[str, str]] = {}  # per source, change_key of the causes last logged
        self._told_safe: dict[str, bool] = {}  # per source, whether the safe mask in force was logged
        self._thread = threading.Thread(target=self._control, name="gcdtrav-relay-control", daemon=True)

    def start(self) -> Relay:
        for camera in self.cameras:
            self.freshness.watch(camera.source)
            if self.settings.link_health_period_s is not None:
                self._link_health[camera.source] = Guarded(
                    self.link.declare_publisher(self.keys.relay_health(camera.source), encoding=MSGPACK)
                )
            self.forwarders += self.robot.outputs(self, camera.source)
            self._declared += camera.start()
        if self.settings.outcomes is not None:
            self._start_outcomes(self.settings.outcomes)
        self._thread.start()
        log.info(
            "relaying %s to %s (JPEG quality %d, max side %s)",
            ", ".join(f"{c.camera.camera} as {c.source}" for c in self.cameras),
            self.settings.input_prefix,
            self.settings.jpeg_quality,
            self.settings.max_side,
        )
        return self

    def _start_outcomes(self, settings: RelayOutcomes) -> None:
        source = self.settings.outcome_source()
        outcomes = Guarded(self.link.declare_publisher(self.keys.outcomes(source), encoding=MSGPACK))
        path = Guarded(self.link.declare_publisher(self.keys.planned_path(source), encoding=MSGPACK))
        self.outcomes = OutcomeLink(settings, source, outcomes, path)
        self._declared += [outcomes, path, *self.robot.subscribe_outcomes(self.outcomes)]
        log.info("measuring outcomes of grid %s on the robot, sent every %g s at most", source, settings.batch_period_s)

    def outcome_uplink(self, source: str) -> float:
        """Bytes per second of outcomes sent for the grid ``source`` (a camera's health counts them)."""
        outcomes = self.outcomes
        return outcomes.uplink.per_s() if outcomes is not None and outcomes.source == source else 0.0

    def wake(self) -> None:
        self._wake.set()

    def tell_link_now(self) -> None:
        """Send every camera's health over the link at the control thread's next turn (a camera parked)."""
        self._link_due.set()
        self._wake.set()

    def grant_seen(self, source: str, grant: CreditGrant) -> None:
        """A credit also says how fresh the owner's maps are; it counts while no maps are forwarded."""
        if grant.last_maps_stamp is not None and not any(f.active for f in self.forwarders if f.source == source):
            self.freshness.observe(source, self.camera(source).camera_clock.on_host_clock(grant.last_maps_stamp))

    def observe_output(self, source: str, stamp: float) -> None:
        """An output of the camera's frame stamped ``stamp`` (the camera's clock) reached the robot."""
        self.freshness.observe(source, self.camera(source).camera_clock.on_host_clock(stamp))

    def camera(self, source: str) -> CameraLink:
        return next(camera for camera in self.cameras if camera.source == source)

    # ---- the speed masks' guards (client/relay/mask_guard.py) ---------------------------------------------
    def heard(self, source: str) -> None:
        """A message of the service about ``source`` arrived (a credit, any output)."""
        guard = self.guards.get(source)
        if guard is not None:
            guard.heard()

    def robot_pose(self, x: float, y: float, frame_id: str) -> None:
        """The robot's newest pose: where a safe mask is centred (every camera of the robot)."""
        for guard in self.guards.values():
            guard.pose(x, y, frame_id)

    def mask_arrived(self, source: str, payload: bytes) -> bool:
        """A live speed mask of ``source`` (OccupancyGrid CDR) arrived: whether to put it in force."""
        guard = self.guards.get(source)
        if guard is None:
            return True
        try:
            geometry = occupancy_grid_geometry(payload)
        except RosNavError as err:
            log.warning("%s: a speed mask that is not one, not put in force: %s", source, err)
            return False
        accepted = guard.live_mask(geometry, mask_age_s(self.camera(source), geometry.stamp))
        if accepted and guard.safe_masks and self._told_safe.get(source):
            self._told_safe[source] = False
            log.info("%s: a fresh speed mask from the service is in force again", source)
        return accepted

    def safe_mask_reason(self, source: str) -> str | None:
        guard = self.guards.get(source)
        return guard.reason if guard is not None and guard.state == SAFE else None

    def _guard(self) -> None:
        for guard in self.guards.values():
            with guard.turn:  # decided and put as one step: never after a fresh live mask that came meanwhile
                mask = guard.due()
                if mask is not None:
                    self._put_safe_mask(mask)

    def _put_safe_mask(self, mask: SafeMask) -> None:
        if not self._told_safe.get(mask.source):
            self._told_safe[mask.source] = True
            log.warning(
                "%s: the safe speed mask (%d %% everywhere) is in force: %s", mask.source, mask.percent, mask.reason
            )
        try:
            self.robot.publish_safe_mask(mask)
        except zenoh.ZError as err:  # the robot's session is closing
            log.debug("%s: the safe mask not put: %s", mask.source, err)

    def health(self, source: str) -> RelayHealth:
        downlink = sum(f.downlink.per_s() for f in self.forwarders if f.source == source)
        return self.camera(source).health(self.freshness, downlink, self.settings.stale_after_s)

    # ---- the control thread: subscriptions on demand, health, staleness ----------------------------
    def _control(self) -> None:
        next_health = next_link = time.monotonic()
        link_period = self.settings.link_health_period_s
        while not self.stopping:
            due = min(next_health, next_link) if link_period is not None else next_health
            if self.guards:
                due = min(due, time.monotonic() + GUARD_PERIOD_S)
            if self.outcomes is not None:
                due = min(due, self.outcomes.send_due())
            self._wake.wait(max(0.0, due - time.monotonic()))
            self._wake.clear()
            if self.stopping:
                return
            self._guard()
            for forwarder in self.forwarders:
                forwarder.reconcile()
            if time.monotonic() >= next_health:
                next_health += self.settings.health_period_s
                self._report()
            if link_period is not None and (time.monotonic() >= next_link or self._link_due.is_set()):
                self._link_due.clear()
                next_link = time.monotonic() + link_period
                self._report_over_link()

    def _report_over_link(self) -> None:
        for camera in self.cameras:
            try:
                self._link_health[camera.source].put(self.health(camera.source).pack())
            except zenoh.ZError as err:  # the link session is closing
                log.debug("%s: health over the link failed: %s", camera.source, err)

    def _report(self) -> None:
        for change in self.freshness.check():
            self._log_change(change)
            if self._on_stale is not None:
                self._on_stale(change)
        for camera in self.cameras:
            health = self.health(camera.source)
            self.robot.publish_health(health)
            self._log_causes(camera.source, health.causes)

    def _log_causes(self, source: str, found: dict[str, str]) -> None:
        """Once per change of the causes, not at every report."""
        key, told = change_key(found), self._told_causes.get(source, {})
        if key == told:
            return
        self._told_causes[source] = key
        if found:
            log.warning("%s: %s", source, "; ".join(f"{code}: {text}" for code, text in found.items()))
        else:
            log.info("%s: no cause of staleness known any more (was %s)", source, ", ".join(told))

    def _log_change(self, change: Staleness) -> None:
        if change.stale:
            self._log_stale(change.source, self.health(change.source))
        else:
            log.info("maps of %s fresh again: %.1f s old", change.source, change.age_s)

    def _log_stale(self, source: str, health: RelayHealth) -> None:
        why = f"; why: {health.problem}" if health.problem else ""
        if health.map_age_s is None:
            waited = time.time() - self.started_at
            log.warning("no maps of %s yet, %.1f s after the relay started%s", source, waited, why)
        else:
            log.warning(
                "maps of %s stale for %.1f s (newest %.1f s old; %d frames sent, %d credit timeouts)%s",
                source,
                health.map_age_s - self.settings.stale_after_s,
                health.map_age_s,
                health.frames_sent,
                health.credit_timeouts,
                why,
            )

    def close(self) -> None:
        self.stopping = True
        self._wake.set()
        for camera in self.cameras:
            camera.stop()
        self._thread.join(5)
        if self.outcomes is not None:
            self.outcomes.send_due(force=True)  # what was measured since the last batch, not lost at a stop
        for forwarder in self.forwarders:
            forwarder.close()
        for entity in [*self._declared, *self._link_health.values()]:
            entity.undeclare()
        self._declared.clear()
        self._link_health.clear()
        self.robot.close()
