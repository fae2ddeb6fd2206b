"""The experience's command and odometry inputs decoded (docs/calibration.md): ROS CDR (a topic starting with
'/': geometry_msgs/msg/Twist, nav_msgs/msg/Odometry) or msgpack or JSON on a zenoh key (``Twist2D``,
``Odometry2D``). What they are graded by, the velocity tracker, is the relay's too: schemas/outcomes.py.
"""

from __future__ import annotations

from gcdtrav.schemas.experience import Odometry2D, Twist2D
from gcdtrav.schemas.messages import check_size
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
