"""Bad input from the robot's ROS graph to `gcdtrav relay --ros` (real rclpy over Fast DDS on loopback): an
encoding the service cannot use, a CameraInfo with zero focal length, a frame_id too long, a 50 MB image, a
topic of the wrong type. Each: one log line, a cause in /diagnostics, no crash; the good camera keeps sending.

One relay serves all the cameras (as on a robot): the bad ones must not hold the good one up. The link is a
zenoh peer that listens and counts the frames arriving (no service: the relay sends on credit timeouts).
"""

from __future__ import annotations

import random
import subprocess
import threading
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
import yaml
import zenoh
from conftest import textured_image
from real_components import require_rclpy
from zenoh_helpers import free_port, wait_until

require_rclpy()

from gcdtrav.client.session.zenoh_args import zenoh_config  # noqa: E402

from tools.ros2_robot import (  # noqa: E402
    Camera,
    LogFile,
    Received,
    RosRobot,
    diagnostic_values,
    relay_command,
    ros_environment,
    stop_process,
)

DOMAIN = random.randint(100, 200)
BIG_SIDE = 4096  # 4096 x 4096 rgb8: 50.3 MB
CAMERAS = {
    "good": "/bad/good/image_raw",  # good frames, but its CameraInfo has a zero focal length
    "encoding": "/bad/encoding/image_raw",
    "frame_id": "/bad/frame_id/image_raw",
    "big": "/bad/big/image_raw",
    "type": "/bad/type/image_raw",
}


@dataclass
class Scene:
    diagnostics: Received
    log: LogFile
    arrived: Counter[str]
    relay: subprocess.Popen[Any]


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Scene]:
    from diagnostic_msgs.msg import DiagnosticArray
    from std_msgs.msg import String

    tmp = tmp_path_factory.mktemp("bad_input")
    settings = tmp / "relay.yaml"
    settings.write_text(
        yaml.safe_dump(
            {
                "cameras": [
                    {"camera": topic, "source": f"r1/{name}", "ros_reliable": name == "big"}
                    for name, topic in CAMERAS.items()
                ],
                "credit_timeout_s": 0.3,
                "health_period_s": 0.5,
            }
        )
    )
    port = free_port()
    arrived: Counter[str] = Counter()
    lock = threading.Lock()

    def count(sample: zenoh.Sample) -> None:
        with lock:
            arrived[str(sample.key_expr).removeprefix("gcdtrav/in/")] += 1

    with (
        ros_environment(DOMAIN),
        zenoh.open(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)) as link,
    ):
        link.declare_subscriber("gcdtrav/in/**", count)
        robot = RosRobot("bad_robot")
        pixels = textured_image(48, 64)
        cameras = [
            Camera(robot, CAMERAS["good"], pixels, 10.0, focal=0.0),
            Camera(robot, CAMERAS["encoding"], np.zeros((48, 64 * 4), np.uint8), 10.0, encoding="32FC1"),
            Camera(robot, CAMERAS["frame_id"], pixels, 10.0, frame_id="f" * 300),
            # Reliable, depth 1, both ends: best effort loses a 50 MB frame with any of its fragments.
            Camera(robot, CAMERAS["big"], np.zeros((BIG_SIDE, BIG_SIDE, 3), np.uint8), 0.5, qos=1),
        ]
        wrong = robot.publisher(String, CAMERAS["type"])
        typed = robot.every(0.1, lambda: wrong.publish(String(data="not an image")))
        _, diagnostics = robot.subscribe(DiagnosticArray, "/diagnostics")
        log = LogFile(tmp / "relay.log")
        relay = subprocess.Popen(
            relay_command("--ros", "--settings", str(settings), "-e", f"tcp/127.0.0.1:{port}"),
            stdout=subprocess.DEVNULL,
            stderr=log.handle,
        )
        try:
            yield Scene(diagnostics, log, arrived, relay)
        finally:
            status = stop_process(relay)
            typed.cancel()
            for camera in cameras:
                camera.stop()
            robot.close()
        assert status == 0, log.text()[-2000:]


def cause_of(scene: Scene, name: str, code: str, timeout_s: float = 60.0) -> str:
    def found() -> str | None:
        values = diagnostic_values(scene.diagnostics, f"r1/{name}") or {}
        return values.get(f"cause.{code}")

    assert wait_until(found, timeout_s), (diagnostic_values(scene.diagnostics, f"r1/{name}"), scene.log.text()[-3000:])
    text = found()
    assert text is not None
    return text


def assert_said_once(scene: Scene, name: str, fragment: str) -> None:
    """Said when it began (the relay logs each change of a camera's causes once, all its causes in the line),
    not at every frame: a handful of lines while the camera sent many frames."""
    lines = [line for line in scene.log.text().splitlines() if f"gcdtrav.relay: r1/{name}: " in line]
    assert 1 <= sum(fragment in line for line in lines) <= 3, "\n".join(lines)


def assert_still_serving(scene: Scene) -> None:
    """The relay is alive and the good camera's frames still cross the link."""
    before = scene.arrived["r1/good"]
    assert wait_until(lambda: scene.arrived["r1/good"] >= before + 2, 30), scene.log.text()[-3000:]
    assert scene.relay.poll() is None and "Traceback" not in scene.log.text()


def test_an_encoding_the_service_cannot_use(scene: Scene) -> None:
    text = cause_of(scene, "encoding", "camera_unusable")
    assert "unknown_encoding" in text and "32FC1" in text
    assert_said_once(scene, "encoding", "camera_unusable: camera frame on /bad/encoding/image_raw not usable: unknown")
    assert_still_serving(scene)


def test_a_camera_info_with_zero_focal_length(scene: Scene) -> None:
    text = cause_of(scene, "good", "camera_info_unusable")
    assert "focal length fx=0, fy=0" in text and "/bad/good/image_raw" in text
    assert_said_once(scene, "good", "camera_info_unusable: CameraInfo of '/bad/good/image_raw' has focal length")
    assert_still_serving(scene)  # the frames go on: only a grid needs the intrinsics


def test_a_frame_id_too_long(scene: Scene) -> None:
    text = cause_of(scene, "frame_id", "camera_unusable")
    assert "frame_id_too_long" in text and "300 characters" in text
    assert_said_once(scene, "frame_id", "not usable: frame_id_too_long")
    assert_still_serving(scene)


def test_a_50_mb_image(scene: Scene) -> None:
    text = cause_of(scene, "big", "camera_unusable", timeout_s=90)
    assert "too_large" in text and "over max_camera_bytes = 32000000" in text
    assert int(text.split("too_large: ")[1].split(" bytes")[0]) > BIG_SIDE * BIG_SIDE * 3  # the message's size
    assert_said_once(scene, "big", "camera_unusable: camera frame on /bad/big/image_raw not usable: too_large")
    assert scene.arrived["r1/big"] == 0
    assert_still_serving(scene)


def test_a_topic_of_the_wrong_type(scene: Scene) -> None:
    text = cause_of(scene, "type", "camera_wrong_type")
    assert "'/bad/type/image_raw' is published as std_msgs/msg/String" in text
    assert_said_once(scene, "type", "camera_wrong_type: '/bad/type/image_raw' is published as std_msgs/msg/String")
    values = diagnostic_values(scene.diagnostics, "r1/type") or {}
    assert values["level"] == "2" and values["frames_captured"] == "0"
    assert_still_serving(scene)
