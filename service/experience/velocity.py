"""Velocity-tracking outcomes: how well the robot kept the speed it was commanded (docs/calibration.md).

While the command in force asks for more than ``min_command_mps``, each odometry sample scores
achieved / commanded speed, clipped to [0, 1]; every ``outcome_spacing_m`` driven (or after
``outcome_period_s`` by odometry stamps, for a robot that barely moves) the mean score becomes one
``TraversalOutcome`` of kind ``velocity`` at the mean of the window's positions (where the score was earned),
over the robot's footprint (radius footprint_m / 2). A command is in force for ``command_timeout_s`` after it
was *received* (a Twist carries no stamp, and the robot's clock need not agree with the service's), so the
command's age is judged on the receiving clock for both streams.

Outcomes are spaced by distance, not time: a robot is slow exactly where the ground is bad, so outcomes per
second would sample bad ground more densely than good ground within the same-looking terrain (a bush patch
in a grassy field), and pull the fitted positions down (benchmarks/experience.py measured grass 0.75 and
bush 0.15 for true 0.8 and 0.25 that way).

Inputs come as ROS CDR (a topic starting with '/': geometry_msgs/msg/Twist, nav_msgs/msg/Odometry) or as
msgpack or JSON on a zenoh key (``Twist2D``, ``Odometry2D``).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

from gcdtrav.schemas.experience import Odometry2D, TraversalOutcome, Twist2D
from gcdtrav.schemas.messages import check_size
from gcdtrav.schemas.settings import ExperienceSettings
from gcdtrav.service.ros.cdr import decode_odometry_motion, decode_twist

MAX_INPUT_BYTES = 64 * 1024  # an Odometry CDR with its covariances is about 700 bytes


def is_ros_topic(name: str) -> bool:
    """Settings name a ROS topic with a leading '/', a zenoh key without."""
    return name.startswith("/")


def decode_command(payload: bytes, ros: bool) -> Twist2D:
    """A velocity command: a ROS Twist in CDR, or a Twist2D (msgpack or JSON); MessageError when unusable."""
    if not ros:
        return Twist2D.decode(payload, MAX_INPUT_BYTES)
    check_size("Twist", payload, MAX_INPUT_BYTES)
    vx, vy, wz = decode_twist(payload)
    return Twist2D(vx=vx, vy=vy, wz=wz)


def decode_odometry(payload: bytes, ros: bool) -> Odometry2D:
    """Odometry: a ROS Odometry in CDR, or an Odometry2D (msgpack or JSON); MessageError when unusable."""
    if not ros:
        return Odometry2D.decode(payload, MAX_INPUT_BYTES)
    check_size("Odometry", payload, MAX_INPUT_BYTES)
    pose, (vx, vy, wz) = decode_odometry_motion(payload)
    return Odometry2D(stamp=pose.stamp, frame_id=pose.frame_id, x=pose.x, y=pose.y, yaw=pose.yaw, vx=vx, vy=vy, wz=wz)


@dataclass
class _Window:
    start: float  # odometry stamp of the window's first sample
    total: float = 0.0
    x: float = 0.0  # sums of the samples' positions: the outcome sits at their mean
    y: float = 0.0
    samples: int = 0
    travelled: float = 0.0  # metres since the window's first sample
    last: tuple[float, float] | None = None


class VelocityTracker:
    """One robot's commands and odometry in, velocity outcomes out. Thread-safe (two subscribers feed it)."""

    def __init__(self, settings: ExperienceSettings) -> None:
        self.settings = settings
        self._command: Twist2D | None = None
        self._command_received = -math.inf
        self._window: _Window | None = None
        self._lock = threading.Lock()
        self.counts: dict[str, int] = {}

    def _count(self, name: str) -> None:
        self.counts[name] = self.counts.get(name, 0) + 1

    def on_command(self, command: Twist2D, received_at: float) -> None:
        with self._lock:
            self._command, self._command_received = command, received_at

    def on_odometry(self, odometry: Odometry2D, received_at: float) -> TraversalOutcome | None:
        """Score this sample; the outcome of the period it closes, if any."""
        s = self.settings
        with self._lock:
            command = self._command
            # A command recorded after this sample's receipt is in force too: zenoh runs each subscriber's
            # callback on its own thread, so a newer command can land between the sample's receipt and here.
            fresh = command is not None and received_at - self._command_received <= s.command_timeout_s
            commanded = math.hypot(command.vx, command.vy) if command is not None and fresh else 0.0
            if commanded <= s.min_command_mps:
                self._window = None  # a stop, a turn on the spot or no command: nothing to grade
                self._count("not_commanded")
                return None
            score = min(max(math.hypot(odometry.vx, odometry.vy) / commanded, 0.0), 1.0)
            window = self._window
            if window is None or odometry.stamp < window.start:  # a replayed bag jumped back: start again
                window = self._window = _Window(odometry.stamp)
            window.total += score
            window.x += odometry.x
            window.y += odometry.y
            window.samples += 1
            if window.last is not None:
                window.travelled += math.hypot(odometry.x - window.last[0], odometry.y - window.last[1])
            window.last = (odometry.x, odometry.y)
            if window.travelled < s.outcome_spacing_m and odometry.stamp - window.start < s.outcome_period_s:
                return None
            self._window = _Window(odometry.stamp, last=(odometry.x, odometry.y))  # the next starts here
            self._count("outcomes")
        return TraversalOutcome(
            stamp=odometry.stamp,
            x=window.x / window.samples,
            y=window.y / window.samples,
            score=window.total / window.samples,
            kind="velocity",
            radius_m=s.footprint_m / 2,
        )
