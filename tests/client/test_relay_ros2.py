"""`gcdtrav relay --ros` against real ROS 2: rclpy nodes over Fast DDS on loopback, the relay as a child process,
a real service (tiny random model) on loopback zenoh.

A robot's camera driver publishes Image (front) and CompressedImage (rear) with CameraInfo, and odometry; the
relay, started with ROS parameters, a namespace and a node-name remap, sends them to the service; ROS
subscribers on the robot must receive T, U and the Nav2 costmap with the header stamp of the camera frame
they came from, a late subscriber the latched costmap, and /diagnostics must name a camera that stops.
"""

from __future__ import annotations

import importlib.util
import random
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import textured_image
from real_components import require_rclpy
from zenoh_helpers import wait_until

pytest.importorskip("torch")
require_rclpy()

from gcdtrav.schemas.settings import ServiceSettings  # noqa: E402

from tools.loopback import in_process_service  # noqa: E402
from tools.ros2_robot import (  # noqa: E402
    Camera,
    LogFile,
    Odometry,
    RosRobot,
    diagnostic_values,
    relay_command,
    ros_environment,
    stamp_of,
    stop_process,
)

DOMAIN = random.randint(100, 200)  # this module's own ROS graph: other suites run beside it
FRONT, REAR = "r1/front", "r1/rear"
FLOOR = 0.25  # the speed layer's slowest fraction: ground the grid never saw gets this (25 percent)


@pytest.fixture(scope="module")
def ros_domain() -> Iterator[int]:
    with ros_environment(DOMAIN):
        yield DOMAIN


def service_settings(state_dir: Path) -> ServiceSettings:
    return ServiceSettings.model_validate(
        {
            "state_dir": state_dir,
            "instance": "box-1",
            "preview": False,
            "reuse": {"enabled": False},  # every frame inferred: every one may feed the grid
            "grids": [
                {
                    "source": FRONT,
                    "camera_info_key": "robot/r1/front/camera_info",
                    "mount": {"z": 1.0, "pitch": 0.6},
                    "size_m": 8.0,
                    "resolution_m": 0.25,
                    "pose_key": "robot/r1/pose",
                    "costmap": True,
                    "speed": {"floor": FLOOR, "rate_hz": 10.0},
                }
            ],
        }
    )


def test_camera_to_costmap_through_a_ros2_relay(ros_domain: int, tiny_backend: Any, tmp_path: Path) -> None:
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import OccupancyGrid
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image
    from std_msgs.msg import Bool

    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    with in_process_service(tiny_backend, service_settings(tmp_path)) as (service, port):
        robot = RosRobot("robot_under_test")
        front = Camera(
            robot, "/r1/front/image_raw", textured_image(240, 320), 10.0, frame_id="front_optical", focal=200.0
        )
        rear = Camera(robot, "/r1/rear/image_raw/compressed", textured_image(120, 160, seed=1), 5.0, compressed=True)
        odometry = Odometry(robot, "/r1/odom", 30.0)
        log = LogFile(tmp_path / "relay.log")
        relay = subprocess.Popen(
            relay_command(
                "--ros",
                "-e",
                f"tcp/127.0.0.1:{port}",
                "--stale-after",
                "3",
                "--ros-args",
                "-r",
                "__ns:=/r1",  # relative topics below resolve in the robot's namespace
                "-r",
                "__node:=relay_under_test",
                "-p",
                "camera:=[front/image_raw, rear/image_raw/compressed]",
                "-p",
                f"source:=[{FRONT}, {REAR}]",
                "-p",
                "camera_info_key:=[robot/r1/front/camera_info, '']",
                "-p",
                "odometry_topic:=odom",
                "-p",
                "odometry_key:=robot/r1/pose",
            ),
            stdout=subprocess.DEVNULL,
            stderr=log.handle,
        )
        try:
            _, traversability = robot.subscribe(Image, "/r1/front/image_raw/gcdtrav/traversability")
            _, uncertainty = robot.subscribe(Image, "/r1/front/image_raw/gcdtrav/uncertainty")
            rear_sub, rear_t = robot.subscribe(Image, "/r1/rear/image_raw/compressed/gcdtrav/traversability")
            _, costmap = robot.subscribe(OccupancyGrid, "/r1/front/image_raw/gcdtrav/grid/costmap", latched)
            _, speed_mask = robot.subscribe(OccupancyGrid, "/r1/front/image_raw/gcdtrav/grid/speed_mask", latched)
            _, diagnostics = robot.subscribe(DiagnosticArray, "/diagnostics")

            assert wait_until(lambda: len(traversability) >= 3 and len(uncertainty) >= 3, 120), log.text()[-3000:]
            assert wait_until(lambda: len(rear_t) >= 2, 60), log.text()[-3000:]
            assert wait_until(lambda: len(costmap) >= 1, 60), log.text()[-3000:]
            assert wait_until(lambda: len(speed_mask) >= 1, 60), log.text()[-3000:]

            # T and U: 32FC1 in [0, 1], stamped with the camera frame they came from, to the nanosecond.
            images, rear_images = traversability.messages + uncertainty.messages, list(rear_t.messages)
            front_stamps, rear_stamps = set(front.stamps), set(rear.stamps)  # after the images: none newer
            for image, _ in images:
                assert stamp_of(image) in front_stamps and image.header.frame_id == "front_optical"
                assert image.encoding == "32FC1" and image.step == 4 * image.width
                values = np.frombuffer(bytes(image.data), "<f4")
                assert values.size == image.width * image.height and 0.0 <= values.min() <= values.max() <= 1.0
            assert all(stamp_of(image) in rear_stamps for image, _ in rear_images)  # CompressedImage path

            # The costmap: the grid fused the front camera's frames at the odometry's poses, for Nav2.
            grid = costmap.last
            assert stamp_of(grid) in set(front.stamps) and grid.header.frame_id == "odom"
            cells = np.asarray(grid.data, np.int8)
            assert cells.size == grid.info.width * grid.info.height == 32 * 32 and (cells >= 1).any()

            # A late subscriber gets the last costmap at once (transient local, depth 1).
            _, late = robot.subscribe(OccupancyGrid, "/r1/front/image_raw/gcdtrav/grid/costmap", latched)
            assert wait_until(lambda: len(late) >= 1, 30), "the late subscriber got no latched costmap"
            assert stamp_of(late.messages[0][0]) in set(front.stamps)  # the camera may have sent newer frames

            # The speed filter mask, as Nav2's SpeedFilter reads it: percent of the maximum speed per cell, 0 (no
            # limit) or FLOOR .. 99, never -1 (unknown: an error to SpeedFilter); unseen ground at the floor.
            mask = speed_mask.last
            assert stamp_of(mask) in set(front.stamps) and mask.header.frame_id == "odom"
            percent = np.asarray(mask.data, np.int8)
            assert percent.size == mask.info.width * mask.info.height == 32 * 32
            assert set(np.unique(percent).tolist()) <= {0, *range(round(100 * FLOOR), 100)}, np.unique(percent)
            assert (percent == round(100 * FLOOR)).any()
            if importlib.util.find_spec("nav2_msgs") is None:  # the PyPI wheels: the info is Nav2's to put
                assert log.count(f"{FRONT}: no nav2_msgs here: the speed mask is published") == 1
            _, late_mask = robot.subscribe(OccupancyGrid, "/r1/front/image_raw/gcdtrav/grid/speed_mask", latched)
            assert wait_until(lambda: len(late_mask) >= 1, 30), "the late subscriber got no latched speed mask"
            assert stamp_of(late_mask.messages[0][0]) in set(front.stamps)

            # Outputs cross the link only while a ROS subscriber exists: the rear camera's costmap never did,
            # its T stops crossing when its subscriber goes.
            assert log.count("forwarding gcdtrav/out/r1/rear/grid/costmap") == 0
            assert log.count("forwarding gcdtrav/out/r1/rear/grid/speed_mask") == 0
            assert log.count("forwarding gcdtrav/out/r1/front/grid/speed_mask") == 1
            robot.destroy(rear_sub)
            assert wait_until(lambda: log.count("no longer forwarding gcdtrav/out/r1/rear/maps8") == 1, 30)

            # Health on /diagnostics, named by the remapped node; the camera stopping shows up as silent.
            def front_health() -> dict[str, str] | None:
                return diagnostic_values(diagnostics, FRONT)

            assert wait_until(lambda: (front_health() or {}).get("owner") == "box-1", 30)
            assert (front_health() or {})["name"] == f"relay_under_test: {FRONT}"
            front.stop()
            assert wait_until(lambda: "cause.camera_silent" in (front_health() or {}), 30), front_health()
            silent = front_health()
            assert silent is not None and silent["level"] == "2"  # ERROR: no maps can come
            assert "/r1/front/image_raw" in silent["cause.camera_silent"]
            assert silent["parked"] == "false" and service.runtime.presence.heard()[FRONT].parked is False

            # The robot's software says it stopped the camera on purpose: parked, its silence no longer a cause,
            # in /diagnostics and in the health over the link (the service's silent-robot alert pages nobody).
            parked = robot.publisher(Bool, "/r1/front/image_raw/gcdtrav/parked", latched)
            parked.publish(Bool(data=True))
            assert wait_until(lambda: (front_health() or {}).get("parked") == "true", 30), front_health()
            assert wait_until(lambda: "cause.camera_silent" not in (front_health() or {}), 30), front_health()
            assert (front_health() or {})["message"].startswith("parked")
            assert wait_until(lambda: service.runtime.presence.heard()[FRONT].parked is True, 30)
            assert log.count("camera parked (said on /r1/front/image_raw/gcdtrav/parked)") == 1

            # Said again, nothing changes; false: the camera runs again, and its silence is a cause once more.
            parked.publish(Bool(data=True))
            parked.publish(Bool(data=False))
            assert wait_until(lambda: (front_health() or {}).get("parked") == "false", 30), front_health()
            assert wait_until(lambda: service.runtime.presence.heard()[FRONT].parked is False, 30)
            assert wait_until(lambda: "cause.camera_silent" in (front_health() or {}), 30), front_health()
            assert log.count("camera parked") == 1 and log.count("camera runs again") == 1
        finally:
            status = stop_process(relay)
            odometry.stop()
            rear.stop()
            robot.close()
        assert status == 0, f"the relay did not stop cleanly on SIGTERM ({status}): {log.text()[-2000:]}"
        assert "Traceback" not in log.text()


def test_sigint_stops_the_node_cleanly(ros_domain: int, tmp_path: Path) -> None:
    """Ctrl-C: exit 0, no traceback, even with no service reachable (a zenoh peer that listens, nothing else)."""
    import zenoh
    from gcdtrav.client.session.zenoh_args import zenoh_config
    from zenoh_helpers import free_port

    port = free_port()
    with zenoh.open(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)):
        log = LogFile(tmp_path / "relay.log")
        relay = subprocess.Popen(
            relay_command("-e", f"tcp/127.0.0.1:{port}", "--ros-args", "-p", "camera:=/cam", "-p", "source:=c"),
            stdout=subprocess.DEVNULL,
            stderr=log.handle,
        )
        assert wait_until(lambda: log.count("relaying /cam as c") == 1, 60), log.text()
        relay.send_signal(signal.SIGINT)
        assert relay.wait(20) == 0, log.text()
        assert "Traceback" not in log.text()


def test_a_bad_parameter_is_a_usage_error(ros_domain: int, tmp_path: Path) -> None:
    began = time.monotonic()
    result = subprocess.run(
        relay_command("--ros", "--ros-args", "-p", "camera:=[/a, /b]", "-p", "source:=only_one"),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2 and "2 camera, 1 source" in result.stderr, result.stderr
    assert time.monotonic() - began < 60


def test_use_sim_time_stamps_the_diagnostics(ros_domain: int, tmp_path: Path) -> None:
    """With use_sim_time the node's clock is /clock's: a bag replayed, a simulator. The outputs keep the camera's
    stamps (whatever clock they are on); the health the node stamps itself follows the simulated time."""
    import zenoh
    from builtin_interfaces.msg import Time
    from diagnostic_msgs.msg import DiagnosticArray
    from gcdtrav.client.session.zenoh_args import zenoh_config
    from rosgraph_msgs.msg import Clock
    from zenoh_helpers import free_port

    port = free_port()
    robot = RosRobot("simulator")
    clock = robot.publisher(Clock, "/clock")
    ticking = robot.every(0.05, lambda: clock.publish(Clock(clock=Time(sec=1000, nanosec=5))))
    _, diagnostics = robot.subscribe(DiagnosticArray, "/diagnostics")
    log = LogFile(tmp_path / "relay.log")
    with zenoh.open(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)):
        relay = subprocess.Popen(
            relay_command(
                "-e",
                f"tcp/127.0.0.1:{port}",
                "--ros-args",
                "-p",
                "camera:=/sim/image",
                "-p",
                "source:=sim",
                "-p",
                "use_sim_time:=true",
            ),
            stdout=subprocess.DEVNULL,
            stderr=log.handle,
        )
        try:

            def stamps() -> set[tuple[int, int]]:
                ours = [array for array, _ in diagnostics.messages if array.status[0].name.endswith(": sim")]
                return {(array.header.stamp.sec, array.header.stamp.nanosec) for array in ours}

            assert wait_until(lambda: (1000, 5) in stamps(), 60), (stamps(), log.text())
            assert stamps() <= {(0, 0), (1000, 5)}, stamps()  # (0, 0): before the first /clock; never the wall
        finally:
            status = stop_process(relay)
            ticking.cancel()
            robot.close()
    assert status == 0, log.text()
