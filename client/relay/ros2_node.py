"""`gcdtrav relay --ros`: the relay as a ROS 2 node (rclpy), for robots on any RMW (Fast DDS, Cyclone DDS,
rmw_zenoh). Imported only for ``--ros``: the base install stays ROS-free; on a robot, rclpy and the message
packages are the robot's own (``source /opt/ros/<distro>/setup.bash``).

The node takes from the robot's ROS graph what the service needs and sends it as today's relay does
(client/relay/relay.py: the newest frame per credit, shrunk, JPEG):

- each camera: sensor_msgs/Image or CompressedImage, the type from the graph (sensor-data QoS: best effort,
  so reliable and best-effort drivers both match), taken as serialized bytes: only frames sent are decoded
  (schemas/ros_image.py, the service's reader); a topic of another type is a health cause, not a crash;
- its CameraInfo: checked (focal length, size), sent as CDR to ``camera_info_key`` on change and every
  ``camera_info_period_s``;
- odometry: a Pose2D to ``odometry.key`` at most ``max_rate_hz`` (the service's grid pose stream).

And it publishes the service's outputs into the graph, each fetched over the link only while a ROS
subscriber counts on it (``get_subscription_count``, polled every ``GRAPH_PERIOD_S``):

- ``<camera topic>/gcdtrav/traversability`` and ``.../uncertainty``: sensor_msgs/Image 32FC1 at the maps' size,
  reliable, volatile, depth 10, with the header (stamp to the nanosecond, frame id) of the camera frame;
- ``<camera topic>/gcdtrav/grid/costmap``: nav_msgs/OccupancyGrid, reliable, transient local, depth 1 (Nav2's
  static layer, RViz's Map display get the last one when they join);
- ``<camera topic>/gcdtrav/grid/speed_mask``: the speed filter mask (a grid with ``speed:``), nav_msgs/OccupancyGrid
  with the same QoS, as Nav2's SpeedFilter subscribes; where the robot has nav2_msgs (a robot that runs Nav2
  does), also ``.../speed_filter_info`` (CostmapFilterInfo naming the mask's topic, transient local, put once per
  change: each new info makes SpeedFilter subscribe again) and ``.../speed_limit`` (SpeedLimit, volatile). The
  PyPI wheels have no nav2_msgs: there the info comes from Nav2's costmap_filter_info_server (examples/nav2);
- ``/diagnostics``: diagnostic_msgs/DiagnosticArray, one status per camera, every ``health_period_s``.

The robot's software says a camera is stopped on purpose with std_msgs/Bool on ``<camera topic>/gcdtrav/parked``
(true: parked; false: runs again; reliable, transient local, depth 1): the relay's ``CameraParked``, so a parked
robot's silence pages nobody.

tf is not relayed: no tf2_msgs package is assumed (the PyPI wheels have none); grids take the pose from
odometry and the mount from the service's settings.
"""

from __future__ import annotations

import importlib
import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from functools import partial
from typing import Any

import numpy as np
import rclpy
import zenoh
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from gcdtrav.client.client import Maps
from gcdtrav.client.relay.causes import (
    CAMERA_INFO_UNUSABLE,
    CAMERA_SILENT,
    CAMERA_UNUSABLE,
    CAMERA_WRONG_TYPE,
    NO_INSTANCE,
)
from gcdtrav.client.relay.link import MSGPACK, Guarded, OnDemand
from gcdtrav.client.relay.mask_guard import SafeMask
from gcdtrav.client.relay.outcomes import OutcomeLink
from gcdtrav.client.relay.relay import CameraLink, CapturedFrame, Relay
from gcdtrav.client.relay.ros_parameters import PARAMETERS, as_list, camera_info_topic, settings_overrides
from gcdtrav.schemas.messages import CameraParked, MessageError, Pose2D, RelayHealth
from gcdtrav.schemas.outcomes import decode_command, decode_contact
from gcdtrav.schemas.relay import RelayCamera, RelayOdometry, RelaySettings
from gcdtrav.schemas.ros_image import COMPRESSED_IMAGE, IMAGE, SUPPORTED_TYPES, peek_stamp
from gcdtrav.schemas.ros_nav import (
    RosNavError,
    costmap_filter_info_cdr,
    occupancy_grid_geometry,
    odometry_motion,
    path_points,
    restamped,
    speed_limit_cdr,
)
from gcdtrav.schemas.settings.ros import RosOutput as OutputTopics
from gcdtrav.schemas.settings.ros import output_topic
from geometry_msgs.msg import Twist, TwistStamped
from nav_msgs.msg import OccupancyGrid, Odometry, Path
from numpy.typing import NDArray
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rclpy.serialization import serialize_message
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Bool, Header

log = logging.getLogger("gcdtrav.relay")

NODE_NAME = "gcdtrav_relay"
GRAPH_PERIOD_S = 0.25  # how often subscriber counts and camera types are read from the graph
SENSOR_QOS = qos_profile_sensor_data  # best effort, keep last 5: matches reliable and best-effort publishers
RELIABLE_CAMERA_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE)  # the newest frame only
IMAGE_QOS = QoSProfile(depth=10)  # rclcpp's default publisher profile, as the service's own ROS outputs
LATCHED_QOS = QoSProfile(
    depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
)  # a map: a subscriber that joins later gets the last one
MESSAGE_CLASSES: dict[str, Any] = {IMAGE: Image, COMPRESSED_IMAGE: CompressedImage}
ERROR_CAUSES = (CAMERA_SILENT, CAMERA_UNUSABLE, CAMERA_WRONG_TYPE, NO_INSTANCE)  # no maps can come at all
NAMES = OutputTopics()  # the service's own output topics (their default templates): the relay publishes under them
PARKED = "gcdtrav/parked"  # std_msgs/Bool from the robot's software: the camera is stopped on purpose


def ros_time(sec_nanosec: tuple[int, int]) -> Time:
    return Time(sec=sec_nanosec[0], nanosec=sec_nanosec[1])


def nav2_messages() -> tuple[Any, Any, Any] | None:
    """nav2_msgs' CostmapFilterInfo, SpeedLimit and Costmap classes where the robot has them (one that runs Nav2
    does); None where not (the PyPI wheels): rclpy publishes only types whose type support it can load."""
    try:
        module = importlib.import_module("nav2_msgs.msg")
    except ImportError:
        return None
    return module.CostmapFilterInfo, module.SpeedLimit, module.Costmap


def float_image(values: NDArray[np.float32], header: Header) -> Image:
    """A 32FC1 sensor_msgs/Image, little-endian."""
    height, width = values.shape
    return Image(
        header=header,
        height=height,
        width=width,
        encoding="32FC1",
        is_bigendian=0,
        step=4 * width,
        data=np.ascontiguousarray(values, dtype="<f4").tobytes(),
    )


def set_cause(link: CameraLink, code: str, text: str | None) -> None:
    """A cause the graph shows (or None: gone); the relay logs each change of a camera's causes once. A new
    dict: the health reads it from another thread."""
    if link.graph_causes.get(code) == text:
        return
    causes = {key: value for key, value in link.graph_causes.items() if key != code}
    if text is not None:
        causes[code] = text
    link.graph_causes = causes


class RosCamera:
    """One camera's topics in the graph: its image (the type as the graph publishes it) and its CameraInfo."""

    def __init__(self, side: RosRobotSide, link: CameraLink) -> None:
        self.side, self.link, self.camera = side, link, link.camera
        self.topic = side.node.resolve_topic_name(self.camera.camera)  # namespace and remapping applied
        self.msgtype: str | None = None
        self._subscription: Any = None
        self._info_sent: tuple[Any, ...] | None = None
        self._info_sent_at = -math.inf
        self._info_publisher: Guarded | None = None
        self.parked_topic = f"{self.topic}/{PARKED}"
        side.node.create_subscription(Bool, self.parked_topic, self.on_parked, LATCHED_QOS)
        info_topic = self.camera.camera_info
        if info_topic is not None:
            name = camera_info_topic(self.topic) if info_topic == "auto" else info_topic
            side.node.create_subscription(CameraInfo, name, self.on_camera_info, SENSOR_QOS)
            if self.camera.camera_info_key is not None:
                self._info_publisher = Guarded(side.link.declare_publisher(self.camera.camera_info_key))
        self.check_graph()

    def check_graph(self) -> None:
        """Subscribe once the graph says the topic's type; name a type that is no image as a cause."""
        published = {info.topic_type for info in self.side.node.get_publishers_info_by_topic(self.topic)}
        configured = self.camera.ros_message_type
        usable = SUPPORTED_TYPES if configured == "auto" else (configured,)
        wrong = sorted(published - set(usable))
        set_cause(
            self.link,
            CAMERA_WRONG_TYPE,
            f"'{self.topic}' is published as {', '.join(wrong)}, not {' or '.join(usable)}: no frame can come"
            if wrong and not published & set(usable)
            else None,
        )
        if self._subscription is not None:
            return
        found = [msgtype for msgtype in usable if msgtype in published]
        msgtype = configured if configured != "auto" else (found[0] if found else None)
        if msgtype is None:
            return
        self.msgtype = msgtype
        qos = RELIABLE_CAMERA_QOS if self.camera.ros_reliable else SENSOR_QOS
        self._subscription = self.side.node.create_subscription(
            MESSAGE_CLASSES[msgtype], self.topic, self.on_image, qos, raw=True
        )
        log.info("%s: subscribed to %s (%s)", self.link.source, self.topic, msgtype)

    def on_image(self, data: bytes) -> None:
        self.link.keep(CapturedFrame(data, self.msgtype or "", self.topic, time.time(), ros_type=self.msgtype))

    def on_parked(self, parked: Bool) -> None:
        """The robot's software stopped the camera on purpose (true) or runs it again (false)."""
        self.link.park(CameraParked(parked=bool(parked.data), reason=f"said on {self.parked_topic}"[:200]))

    def on_camera_info(self, info: CameraInfo) -> None:
        fx, fy = float(info.k[0]), float(info.k[4])
        problem = None
        if not (fx > 0 and fy > 0 and math.isfinite(fx) and math.isfinite(fy)):
            problem = f"CameraInfo of '{self.topic}' has focal length fx={fx:g}, fy={fy:g}: not sent"
        elif info.width == 0 or info.height == 0:
            problem = f"CameraInfo of '{self.topic}' gives no image size ({info.width}x{info.height}): not sent"
        set_cause(self.link, CAMERA_INFO_UNUSABLE, problem)
        if problem is not None or self._info_publisher is None:
            return
        content = (info.width, info.height, tuple(info.k), tuple(info.d), info.header.frame_id)
        now = time.monotonic()
        if content == self._info_sent and now - self._info_sent_at < self.side.settings.camera_info_period_s:
            return
        self._info_sent, self._info_sent_at = content, now
        self._info_publisher.put(serialize_message(info))

    def close(self) -> None:
        if self._info_publisher is not None:
            self._info_publisher.undeclare()


class RosOutput(OnDemand):
    """One output of one source as ROS topics, fetched over the link only while a ROS subscriber exists."""

    wanted_by = "a ROS subscriber on the robot"

    def __init__(
        self, relay: Relay, source: str, kind: str, publishers: Sequence[Publisher], publish: Callable[[bytes], float]
    ) -> None:
        super().__init__(relay, source, kind)
        self.publishers, self._publish = publishers, publish
        self._told_bad = False

    def poll(self) -> bool:
        """Whether anyone subscribes now; True when that changed."""
        return self.want(any(publisher.get_subscription_count() > 0 for publisher in self.publishers))

    def deliver(self, sample: zenoh.Sample) -> float | None:
        try:
            return self._publish(sample.payload.to_bytes())
        except Exception as err:  # bad bytes from the link: msgpack, PNG, CDR and rclpy raise their own error types
            if not self._told_bad:
                log.warning("%s: not published on the robot, not readable: %s", self.key, err)
            self._told_bad = True
            return None


def restamping(publisher: Publisher, link: CameraLink) -> Callable[[bytes], float]:
    """Publish a stamped message's CDR as it came, stamped with the camera frame's exact stamp (a float loses its
    nanoseconds); return the stamp."""

    def publish(payload: bytes) -> float:
        stamp = peek_stamp(payload)
        if stamp is None:
            raise RosNavError(f"not a stamped message's CDR: {payload[:12]!r}")
        publisher.publish(restamped(payload, link.ros_stamp(stamp)))
        return stamp

    return publish


class SpeedTopics:
    """A grid's speed filter as ROS topics: the mask; its CostmapFilterInfo and the SpeedLimit where the robot
    has nav2_msgs. The info names the mask's topic and the mask's frame: put when that changes, not per mask
    (each new info makes Nav2's SpeedFilter drop its mask and subscribe again)."""

    def __init__(self, node: Node, topic: str, link: CameraLink) -> None:
        self.link = link
        self.mask_topic = output_topic(NAMES.speed_mask_topic, topic)
        self.mask = node.create_publisher(OccupancyGrid, self.mask_topic, LATCHED_QOS)
        nav2 = nav2_messages()
        info_topic, limit_topic = (
            output_topic(NAMES.speed_filter_info_topic, topic),
            output_topic(NAMES.speed_limit_topic, topic),
        )
        self.info = None if nav2 is None else node.create_publisher(nav2[0], info_topic, LATCHED_QOS)
        self.limit = None if nav2 is None else node.create_publisher(nav2[1], limit_topic, IMAGE_QOS)
        self._info_frame: str | None = None
        self._publish_mask = restamping(self.mask, link)
        if nav2 is None:
            log.info(
                "%s: no nav2_msgs here: the speed mask is published on %s, its CostmapFilterInfo and SpeedLimit "
                "are not (docs/ros2.md: Nav2's costmap_filter_info_server puts the info)",
                link.source,
                self.mask_topic,
            )

    def publish_mask(self, payload: bytes) -> float:
        self._announce(occupancy_grid_geometry(payload).frame_id)
        return self._publish_mask(payload)

    def publish_safe(self, mask: SafeMask, now: tuple[int, int]) -> None:
        """The relay's own safe mask (client/relay/mask_guard.py), where the live masks go: announced first, as a
        live one is, or a SpeedFilter that never saw a live mask (a service never heard) would not read it; and,
        where nav2_msgs is, the floor as a SpeedLimit, for a controller that takes the SpeedLimit directly."""
        self._announce(mask.frame_id)
        self.mask.publish(mask.cdr(now))
        if self.limit is not None:
            self.limit.publish(speed_limit_cdr(now, mask.frame_id, mask.percent))

    def _announce(self, frame_id: str) -> None:
        """The CostmapFilterInfo naming the mask's topic, when the mask's frame changes (where nav2_msgs is)."""
        if self.info is not None and frame_id != self._info_frame:
            self._info_frame = frame_id
            self.info.publish(costmap_filter_info_cdr(frame_id, self.mask_topic))

    def outputs(self, relay: Relay, source: str) -> list[RosOutput]:
        mask_publishers = [self.mask] if self.info is None else [self.mask, self.info]
        found = [RosOutput(relay, source, "speed_mask", mask_publishers, self.publish_mask)]
        if self.limit is not None:
            found.append(RosOutput(relay, source, "speed_limit", [self.limit], restamping(self.limit, self.link)))
        return found


class OdometryLink:
    """The robot's odometry, every sample: the safe mask's centre, the outcomes' (with them), and, at most
    ``max_rate_hz``, a grid's pose stream (Pose2D msgpack) when ``key`` is set. Read as CDR by the one rule
    (schemas/ros_nav.py)."""

    def __init__(
        self, node: Node, settings: RelayOdometry, link: zenoh.Session, on_pose: Callable[[float, float, str], None]
    ) -> None:
        self.settings, self.on_pose = settings, on_pose
        self.outcomes: OutcomeLink | None = None  # fed every sample, when the relay measures outcomes
        key = settings.key
        self.publisher = None if key is None else Guarded(link.declare_publisher(key, encoding=MSGPACK))
        self.subscription = node.create_subscription(Odometry, settings.topic, self.on_odometry, SENSOR_QOS, raw=True)
        self.sent = self.rejected = 0
        self._last = -math.inf

    def on_odometry(self, data: bytes) -> None:
        try:
            odometry = odometry_motion(data)
        except MessageError as err:
            if self.rejected == 0:
                log.warning("odometry on %s not usable (counted, said once): %s", self.settings.topic, err)
            self.rejected += 1
            return
        self.on_pose(odometry.x, odometry.y, odometry.frame_id)
        if self.outcomes is not None:
            self.outcomes.on_odometry(odometry)
        now = time.monotonic()
        if self.publisher is None or now - self._last < 1.0 / self.settings.max_rate_hz:
            return
        self._last = now
        pose = Pose2D(stamp=odometry.stamp, frame_id=odometry.frame_id, x=odometry.x, y=odometry.y, yaw=odometry.yaw)
        self.publisher.put(pose.pack())
        self.sent += 1

    def close(self) -> None:
        if self.publisher is not None:
            self.publisher.undeclare()


def decoded(outcomes: OutcomeLink, handle: Callable[[bytes], None], data: bytes) -> None:
    """An input of the outcomes (a message's CDR) decoded and handed over; a bad one counted."""
    try:
        handle(data)
    except MessageError:
        outcomes.rejected += 1


class RosRobotSide:
    """The robot's ROS 2 graph as the relay's robot side (``Relay(robot=...)``)."""

    def __init__(self, node: Node, settings: RelaySettings, link: zenoh.Session) -> None:
        self.node, self.settings, self.link = node, settings, link
        self.cameras: dict[str, RosCamera] = {}
        self.ros_outputs: list[RosOutput] = []
        self.diagnostics = node.create_publisher(DiagnosticArray, "/diagnostics", IMAGE_QOS)
        self.odometry = (
            None if settings.odometry is None else OdometryLink(node, settings.odometry, link, self._on_pose)
        )
        self.speed: dict[str, SpeedTopics] = {}
        self._relay: Relay | None = None
        self._lock = threading.Lock()
        self._timer = node.create_timer(GRAPH_PERIOD_S, self._check_graph)

    def camera_name(self, camera: RelayCamera) -> str:
        return self.node.resolve_topic_name(camera.camera)

    def subscribe_camera(self, link: CameraLink) -> list[Guarded]:
        with self._lock:
            self.cameras[link.source] = RosCamera(self, link)
        return []

    def outputs(self, relay: Relay, source: str) -> list[RosOutput]:
        self._relay = relay
        topic = self.node.resolve_topic_name(relay.camera(source).camera.camera)
        maps_kind = self.settings.ros_maps
        traversability = self.node.create_publisher(Image, output_topic(NAMES.traversability_topic, topic), IMAGE_QOS)
        uncertainty = self.node.create_publisher(Image, output_topic(NAMES.uncertainty_topic, topic), IMAGE_QOS)
        costmap = self.node.create_publisher(OccupancyGrid, output_topic(NAMES.costmap_topic, topic), LATCHED_QOS)
        link = relay.camera(source)

        def publish_maps(payload: bytes) -> float:
            maps = Maps.from_compact_payload(payload) if maps_kind == "maps8" else Maps.from_payload(payload)
            header = Header(stamp=ros_time(link.ros_stamp(maps.header.stamp)), frame_id=maps.header.frame_id)
            traversability.publish(float_image(maps.traversability, header))
            uncertainty.publish(float_image(maps.uncertainty, header))
            return maps.header.stamp

        speed = self.speed[source] = SpeedTopics(self.node, topic, link)
        found = [
            RosOutput(relay, source, maps_kind, [traversability, uncertainty], publish_maps),
            RosOutput(relay, source, "costmap", [costmap], restamping(costmap, link)),
            *speed.outputs(relay, source),
            *self._nav2_costmap(relay, source, topic, link),
        ]
        with self._lock:
            self.ros_outputs += found
        return list(found)

    def _nav2_costmap(self, relay: Relay, source: str, topic: str, link: CameraLink) -> list[RosOutput]:
        """The costmap as a nav2_msgs/Costmap, the collision monitor's source, where the robot has nav2_msgs."""
        nav2 = nav2_messages()
        if nav2 is None:
            return []
        publisher = self.node.create_publisher(nav2[2], output_topic(NAMES.nav2_costmap_topic, topic), LATCHED_QOS)
        return [RosOutput(relay, source, "nav2_costmap", [publisher], restamping(publisher, link))]

    def _check_graph(self) -> None:
        with self._lock:
            cameras, outputs = list(self.cameras.values()), list(self.ros_outputs)
        for camera in cameras:
            camera.check_graph()
        changed = [output.poll() for output in outputs]
        if any(changed) and self._relay is not None:
            self._relay.wake()

    def subscribe_outcomes(self, outcomes: OutcomeLink) -> list[Guarded]:
        """The robot's own commands, odometry (full rate), bumper and planned path, for the outcomes. Commands and
        the bumper with the sensor-data QoS: best effort matches reliable and best-effort publishers alike."""
        settings, node = outcomes.settings, self.node
        stamped = settings.cmd_vel_stamped
        if settings.cmd_vel is not None:
            command = partial(decoded, outcomes, lambda data: outcomes.on_command(decode_command(data, stamped)))
            node.create_subscription(
                TwistStamped if stamped else Twist, settings.cmd_vel, command, SENSOR_QOS, raw=True
            )
        if settings.contact is not None:
            contact = partial(decoded, outcomes, lambda data: outcomes.on_contact(decode_contact(data)))
            node.create_subscription(Bool, settings.contact, contact, SENSOR_QOS, raw=True)
        if settings.planned_path is not None:
            path = partial(decoded, outcomes, lambda data: outcomes.on_path(*path_points(data)))
            node.create_subscription(Path, settings.planned_path, path, IMAGE_QOS, raw=True)
        if self.odometry is None:  # no pose to send: odometry read for the safe mask and the outcomes only
            self.odometry = OdometryLink(node, RelayOdometry(), self.link, self._on_pose)
        self.odometry.outcomes = outcomes
        return []

    def _on_pose(self, x: float, y: float, frame_id: str) -> None:
        if self._relay is not None:
            self._relay.robot_pose(x, y, frame_id)

    def publish_safe_mask(self, mask: SafeMask) -> None:
        speed = self.speed.get(mask.source)
        if speed is not None:
            now = self.node.get_clock().now().seconds_nanoseconds()  # ROS time: simulated with use_sim_time
            speed.publish_safe(mask, (int(now[0]), int(now[1])))

    def publish_health(self, health: RelayHealth) -> None:
        camera = self.cameras.get(health.source)
        relay = self._relay
        topic = camera.topic if camera is not None else health.source
        if camera is None and relay is not None:  # frames: false, no camera subscribed
            topic = self.node.resolve_topic_name(relay.camera(health.source).camera.camera)
        array = DiagnosticArray(status=[diagnostic_status(self.node.get_name(), topic, health)])
        array.header.stamp = self.node.get_clock().now().to_msg()  # ROS time: simulated with use_sim_time
        self.diagnostics.publish(array)

    def close(self) -> None:
        self._timer.cancel()
        if self.odometry is not None:
            self.odometry.close()
        for camera in self.cameras.values():
            camera.close()


def diagnostic_status(node_name: str, topic: str, health: RelayHealth) -> DiagnosticStatus:
    """One camera's health for /diagnostics (rqt_robot_monitor, diagnostic_aggregator): level ERROR when no
    maps can come (a silent or unusable camera, no instance), WARN for other causes or stale maps."""
    causes = health.causes or {}
    if any(code in ERROR_CAUSES for code in causes):
        level = DiagnosticStatus.ERROR
    elif causes or health.stale or health.safe_mask is not None:
        level = DiagnosticStatus.WARN
    else:
        level = DiagnosticStatus.OK
    age = "no maps yet" if health.map_age_s is None else f"maps {health.map_age_s:.1f} s old"
    said = ["parked"] if health.parked else []  # stopped on purpose: its silence is no cause
    said += [f"safe_mask: {health.safe_mask}"] if health.safe_mask is not None else []
    message = "; ".join([*said, age, *(f"{code}: {text}" for code, text in causes.items())])
    figures = {
        "source": health.source,
        "stale": str(health.stale).lower(),
        "parked": str(health.parked).lower(),
        "safe_mask": health.safe_mask or "",
        "map_age_s": "" if health.map_age_s is None else f"{health.map_age_s:.3f}",
        "frames_captured": str(health.frames_captured),
        "frames_sent": str(health.frames_sent),
        "credit_timeouts": str(health.credit_timeouts),
        "uplink_bytes_per_s": f"{health.uplink_bytes_per_s:.0f}",
        "downlink_bytes_per_s": f"{health.downlink_bytes_per_s:.0f}",
        "owner": health.owner or "",
        "clock_offset_s": "" if health.clock_offset_s is None else f"{health.clock_offset_s:.3f}",
    }
    values = [KeyValue(key=key, value=value) for key, value in figures.items()]
    values += [KeyValue(key=f"cause.{code}", value=text) for code, text in causes.items()]
    return DiagnosticStatus(
        level=level, name=f"{node_name}: {health.source}", message=message, hardware_id=topic, values=values
    )


# ---- the node's life: parameters, settings, spin, shutdown ----------------------------------------------
def parameter_values(node: Node) -> dict[str, Any]:
    """The ROS parameters given (``--ros-args -p camera:=/camera/image_raw``, a launch file's), by name."""
    from rcl_interfaces.msg import ParameterDescriptor

    given = {}
    for name in PARAMETERS:
        node.declare_parameter(name, None, ParameterDescriptor(dynamic_typing=True))
        value = node.get_parameter(name).value
        if value is not None:
            given[name] = list(value) if isinstance(value, (list, tuple)) or hasattr(value, "tolist") else value
    return given


def run_node(
    ros_args: list[str],
    settings_file: str | None,
    flag_overrides: dict[str, object],
    link_config: zenoh.Config,
    stop: threading.Event,
) -> int:
    """Run the node until ``stop`` is set (the command's SIGINT/SIGTERM handlers set it); 0, or 2 for bad
    settings (one line on stderr)."""
    import sys

    from gcdtrav.schemas.relay import RelaySettingsError, layered, load_relay_settings
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    context = Context()
    rclpy.init(
        args=["gcdtrav", "--ros-args", *ros_args], context=context, signal_handler_options=SignalHandlerOptions.NO
    )
    try:
        node = Node(NODE_NAME, context=context)
        try:
            parameters = parameter_values(node)
            overrides = layered(flag_overrides, settings_overrides(parameters))
            if "connect" in parameters:
                link_config.insert_json5("connect/endpoints", repr(as_list(parameters["connect"])).replace("'", '"'))
            settings = load_relay_settings(parameters.get("settings", settings_file), overrides)
        except (RelaySettingsError, ValueError) as err:
            print(f"gcdtrav relay: {err}", file=sys.stderr)
            node.destroy_node()
            return 2
        with zenoh.open(link_config) as link:
            relay = Relay(settings, link, robot=RosRobotSide(node, settings, link)).start()
            executor = SingleThreadedExecutor(context=context)
            executor.add_node(node)
            spinner = threading.Thread(target=executor.spin, name="gcdtrav-relay-ros", daemon=True)
            spinner.start()
            log.info("ROS 2 node %s relaying over the link", node.get_fully_qualified_name())
            try:
                stop.wait()
            finally:
                relay.close()
                executor.shutdown(timeout_sec=5)
                spinner.join(5)
                node.destroy_node()
        return 0
    finally:
        if context.ok():
            rclpy.shutdown(context=context)
