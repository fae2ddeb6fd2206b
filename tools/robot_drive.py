"""A simulated robot on the bus, for the experience's loopback test and ``benchmarks/experience.py --bus``: it
drives a synthetic world (tools/synthetic_scene.py) and publishes what a real robot would, over zenoh, to a
service whose grid is ``grid_settings()`` and whose experience reads ``experience_settings()``'s keys:

- its pose (Pose2D) and camera images (PNG: the scene backend reads colours) at 4 Hz of simulated time, each
  image only after the service published the maps of the last one (inferred and fused into the grid, or
  reused for an unchanged view), so that the pose stream is ahead of every frame (the service fuses each
  frame at the pose of its capture stamp, docs/grid.md);
- velocity commands (Twist2D, 1 m/s) at 10 Hz and odometry (Odometry2D) at 20 Hz: to the service's bus, or
  (``robot_bus``) to the robot's own bus, where a relay measures the outcomes (client/relay/outcomes.py).

Simulated time runs faster than the wall clock, from a fixed stamp in the past like a replayed bag (the
settings turn off the age and skew checks made for live robots).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import zenoh
from gcdtrav.client import Maps, TraversabilityClient
from gcdtrav.schemas.experience import Odometry2D, Twist2D
from gcdtrav.schemas.messages import MSGPACK_ENCODING, Pose2D
from gcdtrav.schemas.settings import ExperienceSettings, GridSettings

from tools.synthetic_scene import COMMAND_MPS, Robot, World, default_camera

CAMERA_SOURCE = "robot/cam"
POSE_KEY, CMD_VEL_KEY, ODOMETRY_KEY = "robot/pose", "robot/cmd_vel", "robot/odom"
START_STAMP = 1.7e9
ODOMETRY_DT, COMMAND_EVERY, CAMERA_EVERY = 0.05, 2, 5  # 20 Hz odometry, 10 Hz commands, 4 Hz camera


def grid_settings() -> GridSettings:
    """The grid of the scene's camera, in the pose stream's frame."""
    return default_camera().grid_settings(
        source=CAMERA_SOURCE, pose_key=POSE_KEY, size_m=20.0, resolution_m=0.2, half_life_s=2.0, max_age_s=30.0
    )


def experience_settings(**overrides: object) -> ExperienceSettings:
    fields: dict[str, object] = {"enabled": True, "cmd_vel": CMD_VEL_KEY, "odometry": ODOMETRY_KEY, "footprint_m": 0.6}
    return ExperienceSettings.model_validate(fields | overrides)


class MapsClock:
    """The stamp of the newest maps the service published for the camera's source."""

    def __init__(self) -> None:
        self.stamp = -math.inf
        self.changed = threading.Condition()

    def __call__(self, maps: Maps) -> None:
        with self.changed:
            self.stamp = max(self.stamp, maps.header.stamp)
            self.changed.notify_all()

    def wait_for(self, stamp: float, timeout_s: float) -> None:
        with self.changed:
            if not self.changed.wait_for(lambda: self.stamp >= stamp, timeout_s):
                raise TimeoutError(f"no maps of {stamp} within {timeout_s:g} s (frame rejected or dropped?)")


@dataclass
class BusRobot:
    client: TraversabilityClient
    world: World
    timeout_s: float = 20.0
    # Called after every odometry sample with the robot and its stamp: where examples/experience_drive.py adds
    # a bumper's outcomes and prints its progress.
    after_step: Callable[[Robot, float], None] | None = None
    # Where commands and odometry go: the service's bus (None), or the robot's own, behind a relay.
    robot_bus: zenoh.Session | None = None

    def __post_init__(self) -> None:
        self.maps = MapsClock()
        self._subscriber = self.client.subscribe_maps(CAMERA_SOURCE, self.maps, in_order=False)
        self.encoding = MSGPACK_ENCODING

    def close(self) -> None:
        self._subscriber.undeclare()

    def _put(self, key: str, payload: bytes) -> None:
        self.client.session.put(key, payload, encoding=self.encoding)

    def _put_robot(self, key: str, payload: bytes) -> None:
        if self.robot_bus is None:
            self._put(key, payload)
        else:
            self.robot_bus.put(key, payload, encoding=self.encoding)

    def drive(self, seconds: float, seed: int, start_stamp: float = START_STAMP) -> float:
        """Drive ``seconds`` of simulated time on a route of ``seed``; the last stamp."""
        rng = np.random.default_rng(seed)
        robot, camera = Robot(self.world, rng), default_camera()
        robot.next_goal()
        stamp = start_stamp
        for step in range(int(seconds / ODOMETRY_DT)):
            stamp = start_stamp + step * ODOMETRY_DT
            if step % CAMERA_EVERY == 0:
                image, _ = camera.render(self.world, robot.x, robot.y, robot.yaw)
                self._put(POSE_KEY, Pose2D(stamp=stamp, x=robot.x, y=robot.y, yaw=robot.yaw).pack())
                self.client.publish_image(CAMERA_SOURCE, image, stamp=stamp, compression="png")
                self.maps.wait_for(stamp, self.timeout_s)
            if step % COMMAND_EVERY == 0:
                self._put_robot(CMD_VEL_KEY, Twist2D(vx=COMMAND_MPS).pack())
            speed, rate = robot.step(ODOMETRY_DT)
            odometry = Odometry2D(stamp=stamp, x=robot.x, y=robot.y, yaw=robot.yaw, vx=speed, wz=rate)
            self._put_robot(ODOMETRY_KEY, odometry.pack())
            if self.after_step is not None:
                self.after_step(robot, stamp)
        return stamp
