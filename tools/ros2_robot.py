"""A simulated ROS 2 robot for the tests and the benchmark of `gcdtrav relay --ros`: real rclpy nodes in a
Context of their own (camera drivers publishing Image or CompressedImage with CameraInfo, odometry) and
subscribers of what the relay publishes back. Needs the ROS 2 wheels (tests/requirements-ros2.txt).

Isolation: ``ros_environment(domain)`` sets Fast DDS on loopback only (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST)
in a ROS_DOMAIN_ID of the caller's, so parallel runs do not hear each other.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

ROS_ENVIRONMENT = {"RMW_IMPLEMENTATION": "rmw_fastrtps_cpp", "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}


@contextmanager
def ros_environment(domain: int) -> Iterator[dict[str, str]]:
    """ROS 2 over Fast DDS on loopback in ``domain``, for this process and its children; restored at exit."""
    wanted = ROS_ENVIRONMENT | {"ROS_DOMAIN_ID": str(domain)}
    before = {name: os.environ.get(name) for name in wanted}
    os.environ.update(wanted)
    try:
        yield wanted
    finally:
        for name, value in before.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def relay_command(*arguments: str) -> list[str]:
    """``gcdtrav relay ARGUMENTS`` with this Python (the torch-free path of the CLI)."""
    return [sys.executable, "-m", "gcdtrav.service.commands.cli", "relay", *arguments]


def stamp_now() -> tuple[int, int]:
    now = time.time_ns()
    return now // 1_000_000_000, now % 1_000_000_000


@dataclass
class Received:
    """Messages of one subscription with their arrival (this host's clock, s)."""

    messages: list[tuple[Any, float]] = field(default_factory=list)

    def add(self, message: Any) -> None:
        self.messages.append((message, time.time()))

    def __len__(self) -> int:
        return len(self.messages)

    @property
    def last(self) -> Any:
        return self.messages[-1][0]


class RosRobot:
    """Nodes of a robot in one rclpy Context, spun by one thread; ``close()`` ends them."""

    def __init__(self, name: str = "robot") -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.signals import SignalHandlerOptions

        self.context = Context()
        rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.node = Node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self.executor.spin, name=f"ros-{name}", daemon=True)
        self._thread.start()

    def publisher(self, msg_type: Any, topic: str, qos: Any = 10) -> Any:
        with self._lock:
            return self.node.create_publisher(msg_type, topic, qos)

    def subscribe(self, msg_type: Any, topic: str, qos: Any = 10, raw: bool = False) -> tuple[Any, Received]:
        """``raw``: each message as its CDR bytes."""
        received = Received()
        with self._lock:
            subscription = self.node.create_subscription(msg_type, topic, received.add, qos, raw=raw)
        return subscription, received

    def destroy(self, entity: Any) -> None:
        with self._lock:
            if hasattr(entity, "get_subscription_count"):
                self.node.destroy_publisher(entity)
            else:
                self.node.destroy_subscription(entity)

    def every(self, period_s: float, action: Callable[[], None]) -> Any:
        with self._lock:
            return self.node.create_timer(period_s, action)

    def close(self) -> None:
        import rclpy

        self.executor.shutdown(timeout_sec=5)
        self._thread.join(5)
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)


class Camera:
    """A camera driver: Image (``encoding``) or CompressedImage (JPEG) frames of one picture at ``rate_hz``,
    CameraInfo beside them, each with the exact stamp it published (``stamps``)."""

    def __init__(
        self,
        robot: RosRobot,
        topic: str,
        pixels: np.ndarray,
        rate_hz: float,
        compressed: bool = False,
        encoding: str = "rgb8",
        frame_id: str = "camera_optical",
        focal: float | None = None,
        qos: Any = 10,
    ) -> None:
        from sensor_msgs.msg import CameraInfo, CompressedImage, Image

        self.robot, self.topic, self.frame_id = robot, topic, frame_id
        height, width = pixels.shape[:2]
        if compressed:
            from gcdtrav.schemas.images import encode_jpeg

            self.message: Any = CompressedImage(format="jpeg", data=encode_jpeg(pixels, 90))
        else:
            data = np.ascontiguousarray(pixels).tobytes()
            self.message = Image(height=height, width=width, encoding=encoding, step=len(data) // height, data=data)
        self.publisher = robot.publisher(CompressedImage if compressed else Image, topic, qos)
        self.info: Any = None
        if focal is not None:
            base = topic.removesuffix("/compressed").rsplit("/", 1)[0]
            k = [focal, 0.0, width / 2, 0.0, focal, height / 2, 0.0, 0.0, 1.0]
            self.info = CameraInfo(width=width, height=height, k=k, distortion_model="plumb_bob", d=[0.0] * 5)
            self.info_publisher = robot.publisher(CameraInfo, f"{base}/camera_info")
        self.stamps: list[tuple[int, int]] = []
        self.published_at: dict[tuple[int, int], float] = {}
        self._timer = robot.every(1.0 / rate_hz, self.publish)

    def publish(self) -> None:
        sec, nanosec = stamp_now()
        self.message.header.stamp.sec, self.message.header.stamp.nanosec = sec, nanosec
        self.message.header.frame_id = self.frame_id
        self.publisher.publish(self.message)
        self.stamps.append((sec, nanosec))
        self.published_at[(sec, nanosec)] = time.time()
        if self.info is not None:
            self.info.header = self.message.header
            self.info_publisher.publish(self.info)

    def stop(self) -> None:
        self._timer.cancel()


class Odometry:
    """A robot driving at ``speed`` m/s along x in ``odom``, stamped now, at ``rate_hz``."""

    def __init__(self, robot: RosRobot, topic: str, rate_hz: float, speed: float = 0.5) -> None:
        from nav_msgs.msg import Odometry as OdometryMsg

        self.message = OdometryMsg()
        self.message.header.frame_id, self.message.child_frame_id = "odom", "base_link"
        self.message.pose.pose.orientation.w = 1.0
        self.speed, self.began = speed, time.monotonic()
        self.publisher = robot.publisher(OdometryMsg, topic)
        self._timer = robot.every(1.0 / rate_hz, self.publish)

    def publish(self) -> None:
        sec, nanosec = stamp_now()
        self.message.header.stamp.sec, self.message.header.stamp.nanosec = sec, nanosec
        self.message.pose.pose.position.x = self.speed * (time.monotonic() - self.began)
        self.message.twist.twist.linear.x = self.speed  # what the robot achieved: the outcomes' tracking reads it
        self.publisher.publish(self.message)

    def stop(self) -> None:
        self._timer.cancel()


def stamp_of(message: Any) -> tuple[int, int]:
    return int(message.header.stamp.sec), int(message.header.stamp.nanosec)


def diagnostic_values(arrays: Received, source: str) -> dict[str, str] | None:
    """The key/values of ``source``'s newest status in the DiagnosticArrays received (with ``name``, ``level``
    and ``message``), or None."""
    for array, _ in reversed(list(arrays.messages)):
        for status in array.status:
            values = {value.key: value.value for value in status.values}
            if values.get("source") == source:
                return values | {"name": status.name, "level": str(status.level[0]), "message": status.message}
    return None


class LogFile:
    """A child's stderr in a file: read whenever a test asks, never a pipe that fills."""

    def __init__(self, path: Any) -> None:
        self.path = path
        self.handle = open(path, "w+")  # noqa: SIM115 - lives as long as the child

    def text(self) -> str:
        return self.path.read_text() if self.path.exists() else ""

    def count(self, fragment: str) -> int:
        return sum(fragment in line for line in self.text().splitlines())


def stop_process(process: subprocess.Popen[Any], timeout_s: float = 15.0) -> int:
    """SIGTERM, then kill after ``timeout_s``; the exit status (negative: killed)."""
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
            return -9
    return int(process.returncode)


NO_SHM = "transport/shared_memory/enabled:false"  # or payloads between processes of one host bypass a proxy


def relayed_service_yaml(source: str, camera: str, grid: str = "", rest: str = "", resolution_m: float = 0.25) -> str:
    """A `gcdtrav serve` settings file for one relayed robot's grid (as examples/ros2/service.yaml, every frame
    inferred): ``camera`` the line that gives its intrinsics, ``grid`` more of the grid's lines, ``rest`` more
    top-level sections; indented as YAML under the grid."""
    lines = [
        "instance: box-1", "preview: false", "reuse: {enabled: false}", "grids:", f"  - source: {source}",
        f"    {camera}", "    mount: {z: 1.0, pitch: 0.6}", "    size_m: 8.0", f"    resolution_m: {resolution_m}",
        "    pose_key: robot/r1/pose", *(f"    {line}" for line in grid.splitlines() if line.strip()),
    ]  # fmt: skip
    return "\n".join(lines) + "\n" + rest
