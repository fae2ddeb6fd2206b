"""A robot that loses the service slows down by itself: every way a link dies, with real processes.

A real `gcdtrav serve` (tiny random model) with a grid that has a costmap and a speed layer; `gcdtrav relay
--ros` as a child process; the robot's camera driver, odometry and Nav2's side (a subscriber of the speed mask,
reliable and transient local as SpeedFilter subscribes) as real rclpy nodes over Fast DDS on loopback. Between
the relay and the service: a loopback TCP proxy (tools/shaping_proxy.py, zenoh's shared memory off on both
ends) or a zenoh router of the test's own. Then the service is killed (SIGKILL), frozen (SIGSTOP), silently
partitioned (the proxy stops forwarding without closing), its router restarted, and the link flapped.

For each, on the robot: the relay's safe mask (the floor everywhere, at the guard's coarse resolution) comes at
most ``after_s`` + 0.5 s after the last live map or mask; live masks return once the link does; and no live mask
is ever in force longer than ``after_s`` + 0.5 s past the last sign of the service, nor arrives older than
``after_s`` + 0.5 s. Before this round, the last live mask stayed in force for as long as the link was down.
"""

from __future__ import annotations

import contextlib
import random
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import zenoh
from conftest import textured_image
from real_components import require_rclpy
from zenoh_helpers import free_port, listening, serve_args, start_router, wait_until

pytest.importorskip("torch")
require_rclpy()

from tools.ros2_robot import (  # noqa: E402
    NO_SHM,
    Camera,
    LogFile,
    Odometry,
    RosRobot,
    relay_command,
    relayed_service_yaml,
    ros_environment,
    stop_process,
)
from tools.shaping_proxy import LinkShape, ShapingProxy  # noqa: E402

DOMAIN = random.randint(100, 200)  # this module's own ROS graph: other suites run beside it
SOURCE = "r1/front"
CAMERA = "/r1/front/image_raw"
MASK_TOPIC = f"{CAMERA}/gcdtrav/grid/speed_mask"
T_TOPIC = f"{CAMERA}/gcdtrav/traversability"
FLOOR = 0.25
GRID_RESOLUTION, SAFE_RESOLUTION = 0.25, 1.0  # the relay's safe mask (its default cells) is told apart
SLACK_S = 0.5  # the bound: safe within after_s + 0.5 s
CAMERA_INFO = "camera_info_key: robot/r1/front/camera_info"
SERVICE_SETTINGS = relayed_service_yaml(
    SOURCE, CAMERA_INFO, f"costmap: true\nspeed: {{floor: {FLOOR}, rate_hz: 10.0}}", resolution_m=GRID_RESOLUTION
)


@pytest.fixture(scope="module")
def ros_domain() -> Iterator[int]:
    with ros_environment(DOMAIN):
        yield DOMAIN


@dataclass
class Mask:
    arrived: float  # this host's clock, as the stamps (one host: one clock)
    stamp: float
    safe: bool  # the relay's own safe mask
    centre_x: float


class RobotView:
    """What the robot's Nav2 side sees: every speed mask (in force until the next) and every T map."""

    def __init__(self, robot: RosRobot) -> None:
        from nav_msgs.msg import OccupancyGrid
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import Image

        latched = QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
        )
        self.masks: list[Mask] = []
        self.maps: list[float] = []
        robot.node.create_subscription(OccupancyGrid, MASK_TOPIC, self._on_mask, latched)
        robot.node.create_subscription(Image, T_TOPIC, lambda _: self.maps.append(time.time()), 10)

    def _on_mask(self, grid: Any) -> None:
        safe = abs(grid.info.resolution - SAFE_RESOLUTION) < 1e-6
        if safe:
            assert set(grid.data) == {round(FLOOR * 100)}, "the safe mask is the floor everywhere"
        stamp = grid.header.stamp.sec + grid.header.stamp.nanosec * 1e-9
        centre = grid.info.origin.position.x + grid.info.width * grid.info.resolution / 2
        self.masks.append(Mask(time.time(), stamp, safe, centre))

    def live_since(self, moment: float) -> int:
        return sum(1 for mask in self.masks if not mask.safe and mask.arrived > moment)

    def safe_since(self, moment: float) -> list[Mask]:
        return [mask for mask in self.masks if mask.safe and mask.arrived > moment]

    def last_sign_before(self, moment: float) -> float:
        """The last live map or live mask the robot received before ``moment``."""
        signs = [t for t in self.maps if t <= moment] + [
            m.arrived for m in self.masks if not m.safe and m.arrived <= moment
        ]
        return max(signs)

    def check_never_stale(self, after_s: float, end: float) -> None:
        """No live mask in force longer than after_s + SLACK_S past the last sign of the service, none older than
        that on arrival."""
        masks = list(self.masks)
        for index, mask in enumerate(masks):
            if mask.safe:
                continue
            assert mask.arrived - mask.stamp <= after_s + SLACK_S, f"a live mask {mask.arrived - mask.stamp:.2f} s old"
            until = masks[index + 1].arrived if index + 1 < len(masks) else end
            signs = [t for t in self.maps if mask.arrived <= t <= until]
            last = max([mask.arrived, *signs])
            assert until - last <= after_s + SLACK_S, (
                f"a live mask in force {until - last:.2f} s after the last sign of the service (safe after {after_s})"
            )


@dataclass
class Rig:
    view: RobotView
    odometry: Odometry
    relay_log: LogFile
    service_port: int
    link_port: int  # where the relay's link connects: the service, a proxy or a router
    settings: Path
    model: Path
    state_dir: Path
    service: subprocess.Popen[Any] | None = None
    service_log: LogFile | None = None
    proxy: ShapingProxy | None = None
    router: subprocess.Popen[Any] | None = None

    def robot_x(self) -> float:
        return self.odometry.speed * (time.monotonic() - self.odometry.began)

    def start_service(self, connect: str | None = None) -> None:
        endpoint = ["-e", connect] if connect else ["-l", f"tcp/127.0.0.1:{self.service_port}"]
        self.service_log = LogFile(self.state_dir / f"serve-{time.monotonic_ns()}.log")
        self.service = subprocess.Popen(
            serve_args(
                self.model,
                "--settings",
                str(self.settings),
                "--state-dir",
                str(self.state_dir),
                "--precision",
                "fp32",
                "--cfg",
                NO_SHM,
                *(["-m", "client"] if connect else []),
                *endpoint,
            ),
            stdout=subprocess.DEVNULL,
            stderr=self.service_log.handle,
        )

    def logs(self) -> str:
        service = self.service_log.text()[-2000:] if self.service_log else ""
        return f"relay:\n{self.relay_log.text()[-3000:]}\nservice:\n{service}"

    def wait_live(self, after: float, count: int = 3, timeout_s: float = 90.0) -> None:
        assert wait_until(lambda: self.view.live_since(after) >= count, timeout_s), self.logs()

    def wait_safe(self, fault_at: float, after_s: float) -> Mask:
        assert wait_until(lambda: bool(self.view.safe_since(fault_at)), after_s + 10), (
            "no safe mask on the robot after the link died\n" + self.logs()
        )
        return self.view.safe_since(fault_at)[0]


@contextmanager
def camera_straight_to_the_service(port: int) -> Iterator[None]:
    """JPEG envelopes to the service's input key at 10 Hz over zenoh, not through the relay (rmw_zenoh's path)."""
    from gcdtrav.client.session.zenoh_args import zenoh_config
    from gcdtrav.schemas.images import encode_jpeg
    from gcdtrav.schemas.keys import input_key
    from gcdtrav.schemas.messages import ImageEnvelope, PixelEncoding

    session = zenoh.open(zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False))
    jpeg, stop = encode_jpeg(textured_image(120, 160)), threading.Event()

    def run() -> None:
        while not stop.wait(0.1):
            envelope = ImageEnvelope(stamp=time.time(), encoding=PixelEncoding.JPEG, width=160, height=120, data=jpeg)
            with contextlib.suppress(zenoh.ZError):  # the service killed: its frames go nowhere
                session.put(input_key("gcdtrav/in", SOURCE), envelope.pack())

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(5)
        session.close()


@contextmanager
def rig(tmp_path: Path, model: Path, after_s: float, through: str, frames: bool = True) -> Iterator[Rig]:
    """The service, the relay and the robot; ``through``: "direct" (the relay connects to the service), "proxy"
    (through a TCP proxy, ``link_port`` its port) or "router" (both connect to a router on ``link_port``).
    ``frames`` False: the camera's frames go straight to the service (as an rmw_zenoh robot's do), the relay only
    brings the outputs back and guards the mask (``frames: false``)."""
    settings = tmp_path / "service.yaml"
    intrinsics = "intrinsics: {fx: 100, fy: 100, cx: 80, cy: 60, width: 160, height: 120}"
    settings.write_text(SERVICE_SETTINGS if frames else SERVICE_SETTINGS.replace(CAMERA_INFO, intrinsics))
    service_port = free_port()
    with ExitStack() as stack:
        robot = RosRobot("robot_under_test")
        stack.callback(robot.close)
        camera = Camera(robot, CAMERA, textured_image(120, 160), 10.0, frame_id="front_optical", focal=100.0)
        odometry = Odometry(robot, "/r1/odom", 30.0, speed=0.5)
        stack.callback(camera.stop)
        stack.callback(odometry.stop)
        view = RobotView(robot)
        link_port = service_port
        if through == "proxy":
            proxy = ShapingProxy(("127.0.0.1", service_port), LinkShape(rate_bps=1e9)).start()
            stack.callback(proxy.stop)
            link_port = proxy.port
        if through == "router":
            link_port = free_port()
        handle = Rig(
            view, odometry, LogFile(tmp_path / "relay.log"), service_port, link_port, settings, model, tmp_path
        )
        if through == "router":
            handle.router = start_router(link_port)
            stack.callback(lambda: handle.router is not None and stop_process(handle.router))
            handle.start_service(connect=f"tcp/127.0.0.1:{link_port}")
        else:
            handle.start_service()
        stack.callback(lambda: handle.service is not None and stop_process(handle.service))
        # the relay's link is a zenoh client: it opens only once something listens (the service, or its router)
        assert wait_until(lambda: listening(service_port if through != "router" else link_port), 60), handle.logs()
        relay = subprocess.Popen(
            relay_command(
                "--ros",
                "-e",
                f"tcp/127.0.0.1:{link_port}",
                "--cfg",
                NO_SHM,
                "--safe-after",
                str(after_s),
                "--safe-floor",
                str(FLOOR),
                "--ros-args",
                "-p",
                f"camera:={CAMERA}",
                "-p",
                f"source:={SOURCE}",
                "-p",
                "camera_info_key:=robot/r1/front/camera_info",
                "-p",
                "odometry_topic:=/r1/odom",
                "-p",
                "odometry_key:=robot/r1/pose",
                "-p",
                "max_speed_m_s:=1.0",
                "-p",
                f"frames:={str(frames).lower()}",
            ),
            stdout=subprocess.DEVNULL,
            stderr=handle.relay_log.handle,
        )
        stack.callback(lambda: stop_process(relay))
        if through == "proxy":
            handle.proxy = proxy
        if not frames:
            stack.enter_context(camera_straight_to_the_service(service_port))
        handle.wait_live(0.0, count=3, timeout_s=120)
        yield handle


@pytest.fixture()
def model(tiny_model_dir: Path) -> Path:
    return tiny_model_dir


def test_sigkill_of_the_service_puts_the_safe_mask_and_a_new_service_the_live_ones(
    ros_domain: int, model: Path, tmp_path: Path
) -> None:
    after_s = 2.0
    with rig(tmp_path, model, after_s, "direct") as handle:
        assert handle.service is not None
        handle.service.send_signal(signal.SIGKILL)
        killed_at = time.time()
        handle.service.wait(10)
        safe = handle.wait_safe(killed_at, after_s)
        last = handle.view.last_sign_before(killed_at)
        assert safe.arrived - last <= after_s + SLACK_S, (safe.arrived - last, handle.logs())
        assert abs(safe.centre_x - handle.robot_x()) < 2.0  # centred on the robot (0.5 m/s: a few odometry steps)
        handle.start_service()  # the box comes back: live masks take over at once
        back_at = time.time()
        handle.wait_live(back_at)
        handle.view.check_never_stale(after_s, time.time())
        assert "the safe speed mask (25 % everywhere) is in force" in handle.relay_log.text()
        assert "a fresh speed mask from the service is in force again" in handle.relay_log.text()


def test_a_frozen_service_sigstop_puts_the_safe_mask_and_its_thaw_the_live_ones(
    ros_domain: int, model: Path, tmp_path: Path
) -> None:
    after_s = 1.5
    with rig(tmp_path, model, after_s, "direct") as handle:
        assert handle.service is not None
        handle.service.send_signal(signal.SIGSTOP)  # the connection stays open: no FIN, no reset
        frozen_at = time.time()
        try:
            safe = handle.wait_safe(frozen_at, after_s)
            assert safe.arrived - handle.view.last_sign_before(frozen_at) <= after_s + SLACK_S, handle.logs()
            time.sleep(2.0)  # frozen a while longer: whatever it had queued is old when it thaws
        finally:
            handle.service.send_signal(signal.SIGCONT)
        thawed_at = time.time()
        handle.wait_live(thawed_at)
        handle.view.check_never_stale(after_s, time.time())


def test_a_silent_partition_puts_the_safe_mask_and_its_end_the_live_ones(
    ros_domain: int, model: Path, tmp_path: Path
) -> None:
    after_s = 2.0
    with rig(tmp_path, model, after_s, "proxy") as handle:
        proxy = handle.proxy
        assert proxy is not None
        proxy.outage(True)  # nothing forwarded, nothing closed: as a Wi-Fi drop under TCP
        cut_at = time.time()
        safe = handle.wait_safe(cut_at, after_s)
        assert safe.arrived - handle.view.last_sign_before(cut_at) <= after_s + SLACK_S, handle.logs()
        time.sleep(3.0)
        proxy.outage(False)
        healed_at = time.time()
        handle.wait_live(healed_at)
        handle.view.check_never_stale(after_s, time.time())
        assert "no message from the service about r1/front for" in handle.relay_log.text()


def test_a_restarted_router_puts_the_safe_mask_until_the_service_is_back(
    ros_domain: int, model: Path, tmp_path: Path
) -> None:
    after_s = 2.0
    with rig(tmp_path, model, after_s, "router") as handle:
        router = handle.router
        assert router is not None
        router.send_signal(signal.SIGKILL)
        router.wait(10)
        down_at = time.time()
        safe = handle.wait_safe(down_at, after_s)
        assert safe.arrived - handle.view.last_sign_before(down_at) <= after_s + SLACK_S, handle.logs()
        handle.router = start_router(handle.link_port)
        back_at = time.time()
        handle.wait_live(back_at)
        handle.view.check_never_stale(after_s, time.time())


def test_a_flapping_link_never_leaves_a_stale_live_mask_in_force(ros_domain: int, model: Path, tmp_path: Path) -> None:
    """Up 3 s, down 2 s, for a minute; the guard's after_s (1 s) is shorter than the outages."""
    after_s = 1.0
    with rig(tmp_path, model, after_s, "proxy") as handle:
        proxy = handle.proxy
        assert proxy is not None
        began = time.time()
        outages = []
        while time.time() - began < 60:
            time.sleep(3.0)
            proxy.outage(True)
            outages.append(time.time())
            time.sleep(2.0)
            proxy.outage(False)
        handle.wait_live(time.time(), count=1)
        handle.view.check_never_stale(after_s, time.time())
        for down_at in outages:  # each outage brought the safe mask, each return the live ones before the next
            safe = handle.view.safe_since(down_at)
            assert any(mask.arrived < down_at + after_s + SLACK_S for mask in safe), (down_at, handle.logs())
            back = [m.arrived for m in handle.view.masks if not m.safe and down_at + 2.0 < m.arrived < down_at + 5.0]
            assert back, (down_at, handle.logs())


def test_a_robot_whose_frames_go_straight_to_the_service_gets_the_same_guarantee(
    ros_domain: int, model: Path, tmp_path: Path
) -> None:
    """rmw_zenoh straight to the service: the relay with ``frames: false`` brings the mask to the robot's graph and
    guards it; Nav2's SpeedFilter reads the one topic, which turns safe when the service goes quiet."""
    after_s = 2.0
    with rig(tmp_path, model, after_s, "direct", frames=False) as handle:
        assert handle.service is not None
        handle.service.send_signal(signal.SIGKILL)
        killed_at = time.time()
        handle.service.wait(10)
        safe = handle.wait_safe(killed_at, after_s)
        assert safe.arrived - handle.view.last_sign_before(killed_at) <= after_s + SLACK_S, handle.logs()
        handle.view.check_never_stale(after_s, time.time())
        assert "camera_silent" not in handle.relay_log.text()  # no camera of its own to miss
