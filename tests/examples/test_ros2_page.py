"""docs/ros2.md runs as written: every line of its ``ros2-robot`` block, in order, on this machine standing in
for three (the checkout, the robot, the offboard box), with only Python and ROS 2's wheels.

What the test changes, and why: the robot is a fresh virtual environment (with this machine's packages seen
through ``--system-site-packages``: the ROS 2 wheels and gcdtrav's dependencies, no download); since that
also sees this checkout's gcdtrav, the wheel of step 1 is installed with ``--force-reinstall --no-deps`` so
the relay runs from it; the offboard box's ``gcdtrav serve`` gets a tiny random model, a state dir and a free
loopback port (``OFFBOARD`` is that port); the robot's camera (with its CameraInfo) and odometry are real
rclpy nodes over Fast DDS on loopback. The check: T and the Nav2 costmap come back into the robot's graph."""

from __future__ import annotations

import glob
import random
import re
import shlex
import subprocess
import sys
import venv
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import textured_image
from real_components import require_rclpy
from zenoh_helpers import free_port, serve_args, wait_until

pytest.importorskip("torch")
require_rclpy()

from tools.ros2_robot import Camera, LogFile, Odometry, RosRobot, ros_environment, stop_process  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
DOMAIN = random.randint(100, 200)


def page_lines() -> list[str]:
    """The commands of docs/ros2.md's ros2-robot block, comments dropped."""
    text = (ROOT / "docs" / "ros2.md").read_text("utf-8")
    block = re.search(r"<!-- ros2-robot: begin -->\s*```bash\n(.*?)```\s*<!-- ros2-robot: end -->", text, re.S)
    assert block is not None, "docs/ros2.md lost its ros2-robot block"
    return [line for line in block.group(1).splitlines() if line.strip() and not line.lstrip().startswith("#")]


@pytest.fixture(scope="module")
def ros_domain() -> Iterator[int]:
    with ros_environment(DOMAIN):
        yield DOMAIN


def test_the_page_names_the_four_steps() -> None:
    kinds = [shlex.split(line)[:3] for line in page_lines()]
    assert kinds == [
        ["python", "-m", "pip"],
        ["python", "-m", "pip"],
        ["python", "-m", "pip"],
        ["gcdtrav", "serve", "--settings"],
        ["gcdtrav", "relay", "--ros"],
    ], kinds


def test_the_pages_commands_bring_a_relayed_robots_maps_back(
    ros_domain: int, tiny_model_dir: Path, tmp_path: Path
) -> None:
    from nav_msgs.msg import OccupancyGrid
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    wheel_step, ros_step, install_step, serve_step, relay_step = page_lines()
    robot_env = tmp_path / "robot"
    venv.create(robot_env, system_site_packages=True, with_pip=False)  # pip comes from this machine's site
    robot_python = str(robot_env / "bin" / "python")

    def run(line: str, python: str, **replacements: str) -> None:
        words = shlex.split(line)
        words[0:1] = [python]
        words = [replacements.get(word, word) for word in words]
        words = [match for word in words for match in (sorted(glob.glob(str(tmp_path / word))) or [word])]
        done = subprocess.run(words, cwd=tmp_path, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, f"{line}\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}"

    run(wheel_step, sys.executable, **{".": str(ROOT)})  # step 1: the wheel, in tmp_path/dist
    run(ros_step, robot_python)  # step 2: already there, seen through the system site (no download)
    run(install_step + " --force-reinstall --no-deps", robot_python)
    where = subprocess.run(
        [robot_python, "-c", "import gcdtrav.client.relay.relay as m; print(m.__file__)"],
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    assert where.stdout.startswith(str(robot_env)), where.stdout  # the robot runs the wheel, not this checkout

    port = free_port()
    serve_words = shlex.split(serve_step.rstrip(" &"))
    assert serve_words[:2] == ["gcdtrav", "serve"]
    serve_words = [f"tcp/127.0.0.1:{port}" if word == "tcp/0.0.0.0:7447" else word for word in serve_words]
    service_log = LogFile(tmp_path / "serve.log")
    extra = ["--precision", "fp32", "--state-dir", str(tmp_path / "state")]  # and the tiny model: serve_args
    service = subprocess.Popen(
        serve_args(tiny_model_dir, *serve_words[2:], *extra), cwd=ROOT, stdout=subprocess.DEVNULL,
        stderr=service_log.handle,
    )  # fmt: skip
    robot = RosRobot("robot_of_the_page")
    relay: subprocess.Popen[Any] | None = None
    relay_log = LogFile(tmp_path / "relay.log")
    try:
        camera = Camera(robot, "/camera/front/image_raw", textured_image(120, 160), 10.0, focal=100.0)
        odometry = Odometry(robot, "/odom", 20.0)
        latched = QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
        )
        _, maps = robot.subscribe(Image, "/camera/front/image_raw/gcdtrav/traversability")
        _, costmaps = robot.subscribe(OccupancyGrid, "/camera/front/image_raw/gcdtrav/grid/costmap", latched)
        assert wait_until(lambda: "serving:" in service_log.text(), 120), service_log.text()[-3000:]
        words = shlex.split(relay_step.replace("OFFBOARD", "127.0.0.1").replace(":7447", f":{port}"))
        words[0] = str(robot_env / "bin" / "gcdtrav")  # the console script of the robot's wheel
        relay = subprocess.Popen(words, cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=relay_log.handle)
        logs = lambda: f"relay:\n{relay_log.text()[-3000:]}\nservice:\n{service_log.text()[-3000:]}"  # noqa: E731
        assert wait_until(lambda: len(maps) >= 2 and len(costmaps) >= 1, 120), logs()
        assert costmaps.last.header.frame_id == "odom" and maps.last.encoding == "32FC1"
        camera.stop()
        odometry.stop()
    finally:
        if relay is not None:
            assert stop_process(relay) == 0, relay_log.text()[-2000:]
        stop_process(service)
        robot.close()
    assert "Traceback" not in relay_log.text()
