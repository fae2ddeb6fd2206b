"""Issue 56 with real ROS 2: a robot's own cmd_vel, odometry and bumper as rclpy nodes over Fast DDS, behind
`gcdtrav relay --ros` (a child process), against a real `gcdtrav serve` (tiny random model, experience on,
outcomes only from the bus): the outcomes measured on the robot become pairs in the fleet's store, `gcdtrav
calibration` grades them, and a proposal is made from them; its planned path (nav_msgs/Path) reaches the service
as a PlannedPath."""

from __future__ import annotations

import random
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import textured_image, torch_free_gcdtrav
from real_components import require_rclpy
from zenoh_helpers import client_config, free_port, listening, serve_args, wait_until

pytest.importorskip("torch")
require_rclpy()

from gcdtrav.client import QueryTimeout, ServiceError, TraversabilityClient  # noqa: E402
from gcdtrav.schemas.experience import PlannedPath  # noqa: E402

from tools.ros2_robot import (  # noqa: E402
    Camera,
    LogFile,
    Odometry,
    RosRobot,
    relay_command,
    relayed_service_yaml,
    ros_environment,
    stop_process,
)

DOMAIN = random.randint(100, 200)
SOURCE, CAMERA = "r1/front", "/r1/front/image_raw"
SERVICE_SETTINGS = relayed_service_yaml(
    SOURCE,
    "camera_info_key: robot/r1/front/camera_info",
    rest="""experience:
  enabled: true                     # no cmd_vel or odometry here: the outcomes come from the robot's relay
  lookahead_s: 1.0
  min_pairs_per_anchor: 1
""",
)


@pytest.fixture(scope="module")
def ros_domain() -> Iterator[int]:
    with ros_environment(DOMAIN):
        yield DOMAIN


def test_outcomes_measured_behind_a_ros_relay_are_paired_graded_and_proposed_from(
    ros_domain: int, tiny_model_dir: Path, tmp_path: Path
) -> None:
    from geometry_msgs.msg import PoseStamped, Twist
    from nav_msgs.msg import Path as RosPath
    from std_msgs.msg import Bool

    settings = tmp_path / "service.yaml"
    settings.write_text(SERVICE_SETTINGS)
    port = free_port()
    service_log, relay_log = LogFile(tmp_path / "serve.log"), LogFile(tmp_path / "relay.log")
    arguments = ["--settings", str(settings), "--state-dir", str(tmp_path), "--precision", "fp32"]
    service = subprocess.Popen(
        serve_args(tiny_model_dir, *arguments, "-l", f"tcp/127.0.0.1:{port}"),
        stdout=subprocess.DEVNULL,
        stderr=service_log.handle,
    )
    robot = RosRobot("robot_under_test")
    relay: subprocess.Popen[Any] | None = None
    try:
        camera = Camera(robot, CAMERA, textured_image(120, 160), 10.0, frame_id="front_optical", focal=100.0)
        odometry = Odometry(robot, "/r1/odom", 30.0, speed=0.5)
        commands = robot.publisher(Twist, "/r1/cmd_vel")
        command = Twist()
        command.linear.x = 1.0  # told 1 m/s, doing 0.5: every velocity outcome scores 0.5
        robot.every(0.1, lambda: commands.publish(command))
        bumper = robot.publisher(Bool, "/r1/bumper")
        plans, plan = robot.publisher(RosPath, "/r1/plan"), RosPath()
        plan.header.frame_id = "odom"
        for x in (0.0, 1.0, 2.0):
            pose = PoseStamped()
            pose.pose.position.x, pose.pose.position.y = x, x / 4
            plan.poses.append(pose)
        robot.every(0.5, lambda: plans.publish(plan))
        assert wait_until(lambda: listening(port), 60), service_log.text()
        relay = subprocess.Popen(
            relay_command(
                *("--ros", "-e", f"tcp/127.0.0.1:{port}", "--ros-args"),
                *("-p", f"camera:={CAMERA}", "-p", f"source:={SOURCE}"),
                *("-p", "camera_info_key:=robot/r1/front/camera_info"),
                *("-p", "odometry_topic:=/r1/odom", "-p", "odometry_key:=robot/r1/pose"),
                *("-p", "cmd_vel_topic:=/r1/cmd_vel", "-p", "contact_topic:=/r1/bumper"),
                *("-p", "planned_path_topic:=/r1/plan"),
            ),
            stdout=subprocess.DEVNULL,
            stderr=relay_log.handle,
        )
        logs = lambda: f"relay:\n{relay_log.text()[-3000:]}\nservice:\n{service_log.text()[-3000:]}"  # noqa: E731
        with TraversabilityClient(config=client_config(port), timeout=10.0) as client:
            paths: list[PlannedPath] = []
            client.session.declare_subscriber(
                f"gcdtrav/in/{SOURCE}/planned_path",
                lambda sample: paths.append(PlannedPath.unpack(sample.payload.to_bytes())),
            )

            def counts() -> dict[str, int]:
                try:
                    experience = client.status().experience
                except (QueryTimeout, ServiceError):
                    return {}
                return dict(experience.counts) if experience is not None else {}

            assert wait_until(lambda: counts().get("pairs", 0) >= 30, 120), (counts(), logs())
            bumper.publish(Bool(data=True))  # a press: one contact outcome at the robot's pose
            assert wait_until(lambda: client.calibration(SOURCE).pairs_by_kind.get("contact", 0) > 0, 60), logs()
            report = client.calibration(SOURCE)
            assert report.pairs_by_kind["velocity"] >= 30 and report.figures.pairs == sum(report.pairs_by_kind.values())
            assert counts()["relayed_outcomes"] >= 10 and "velocity_outcomes" not in counts()  # all from the relay
            flags = ["-m", "client", "-e", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"]
            graded = subprocess.run(
                torch_free_gcdtrav("calibration", SOURCE, *flags), capture_output=True, text=True, timeout=60
            )
            assert graded.returncode == 0 and f"calibration of {SOURCE}" in graded.stdout, graded.stdout + graded.stderr
            proposal = client.anchor_proposal()
            assert proposal.train_pairs + proposal.held_out_pairs > 0 and proposal.proposed_version
            assert wait_until(lambda: len(paths) > 0, 30), logs()
            assert paths[-1].frame_id == "odom" and paths[-1].points == [(0.0, 0.0), (1.0, 0.25), (2.0, 0.5)]
        camera.stop()
        odometry.stop()
    finally:
        if relay is not None:
            assert stop_process(relay) == 0, relay_log.text()[-2000:]
        stop_process(service)
        robot.close()
    assert "Traceback" not in relay_log.text()
    assert "measuring outcomes of grid r1/front on the robot" in relay_log.text()
