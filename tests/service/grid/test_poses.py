"""The pose buffer at its edges (service/grid/poses.py, docs/grid.md *Which pose*)."""

from __future__ import annotations

import math
import threading

import pytest
from gcdtrav.schemas.messages import Pose2D
from gcdtrav.schemas.settings import GridSettings, PoseBufferSettings
from gcdtrav.service.grid.poses import AFTER_POSES, BEFORE_POSES, NO_POSE, POSE_GAP, PoseBuffer
from pydantic import ValidationError


def pose(stamp: float, x: float = 0.0, y: float = 0.0, yaw: float = 0.0, frame_id: str = "odom") -> Pose2D:
    return Pose2D(stamp=stamp, frame_id=frame_id, x=x, y=y, yaw=yaw)


def buffer(
    span_s: float = 10.0, max_poses: int = 1000, extrapolate_s: float = 0.1, max_gap_s: float = 0.5
) -> PoseBuffer:
    return PoseBuffer(span_s, max_poses, extrapolate_s, max_gap_s)


def driving(poses: PoseBuffer, until: float, speed: float = 1.0, hz: float = 50.0) -> None:
    for k in range(round(until * hz) + 1):
        poses.add(pose(k / hz, x=speed * k / hz))


def test_between_two_poses_position_is_linear_and_heading_takes_the_shortest_arc() -> None:
    poses = buffer()
    poses.add(pose(10.0, x=0.0, y=0.0, yaw=math.radians(170)))
    poses.add(pose(10.2, x=0.2, y=-0.4, yaw=math.radians(-170)))  # 20 degrees through +-180, not 340 back
    found = poses.at(10.05)
    assert found.reason is None and found.extrapolated_s == 0.0 and found.pose is not None
    assert (found.pose.x, found.pose.y) == pytest.approx((0.05, -0.1))
    assert math.degrees(found.pose.yaw) == pytest.approx(175.0)
    assert math.degrees(poses.at(10.15).pose.yaw) == pytest.approx(-175.0)  # type: ignore[union-attr]
    assert poses.at(10.2).pose == pose(10.2, x=0.2, y=-0.4, yaw=math.radians(-170))  # a stamp held: that pose


def test_no_pose_yet() -> None:
    assert buffer().at(1.0).reason == NO_POSE and buffer().at(1.0).pose is None


def test_a_frame_older_than_the_buffer_has_no_pose_unless_within_the_extrapolation() -> None:
    poses = buffer(span_s=2.0)
    driving(poses, until=5.0)  # keeps 3.0 .. 5.0
    assert poses.at(2.5).reason == BEFORE_POSES
    held = poses.at(2.95)  # 0.05 s before the oldest: the oldest pose, held
    assert held.reason is None and held.pose is not None and held.pose.x == pytest.approx(3.0)
    assert held.extrapolated_s == pytest.approx(0.05)


def test_a_frame_newer_than_the_last_pose_is_extrapolated_a_little_at_the_last_velocity_else_has_none() -> None:
    poses = buffer(extrapolate_s=0.1)
    driving(poses, until=1.0, speed=2.0)
    ahead = poses.at(1.08)
    assert ahead.reason is None and ahead.pose is not None
    assert ahead.pose.x == pytest.approx(2.16) and ahead.extrapolated_s == pytest.approx(0.08)
    assert poses.at(1.11).reason == AFTER_POSES and poses.at(1.11).pose is None
    single = buffer()
    single.add(pose(1.0, x=3.0))
    assert single.at(1.05).pose.x == pytest.approx(3.0)  # type: ignore[union-attr]  # one pose: held


def test_extrapolation_holds_the_last_pose_when_the_one_before_is_across_a_gap() -> None:
    poses = buffer(max_gap_s=0.5)
    poses.add(pose(0.0, x=0.0))
    poses.add(pose(2.0, x=5.0))  # the stream was silent for 2 s: no velocity to trust
    assert poses.at(2.05).pose.x == pytest.approx(5.0)  # type: ignore[union-attr]


def test_a_stream_that_stops_then_resumes_leaves_frames_of_the_gap_without_a_pose() -> None:
    poses = buffer(max_gap_s=0.5)
    driving(poses, until=1.0)
    assert poses.at(1.5).reason == AFTER_POSES  # stopped: frames after it wait, then are not fused
    poses.add(pose(3.0, x=3.0))  # resumed
    assert poses.at(2.0).reason == POSE_GAP
    assert poses.at(0.5).reason is None  # before the gap: as before


def test_poses_out_of_order_take_their_place_by_stamp() -> None:
    in_order, shuffled = buffer(), buffer()
    stamps = [k * 0.02 for k in range(50)]
    for stamp in stamps:
        in_order.add(pose(stamp, x=stamp, yaw=stamp))
    for stamp in stamps[1::2] + stamps[0::2]:
        shuffled.add(pose(stamp, x=stamp, yaw=stamp))
    assert shuffled.out_of_order == 25 and in_order.out_of_order == 0
    for stamp in (0.013, 0.5, 0.97):
        assert shuffled.at(stamp) == in_order.at(stamp)
    shuffled.add(pose(0.5, x=9.0))  # the same stamp again: replaces
    assert len(shuffled) == 50 and shuffled.at(0.5).pose.x == 9.0  # type: ignore[union-attr]


def test_the_buffer_is_bounded_by_time_and_by_count() -> None:
    by_time = buffer(span_s=1.0)
    driving(by_time, until=5.0)
    assert len(by_time) == 51 and by_time.at(3.9).reason == BEFORE_POSES
    by_count = buffer(max_poses=10)
    driving(by_count, until=5.0)
    assert len(by_count) == 10 and by_count.at(4.8).reason is None and by_count.at(4.7).reason == BEFORE_POSES


def test_a_clock_that_steps_back_or_a_new_frame_restarts_the_buffer() -> None:
    poses = buffer(span_s=2.0)
    driving(poses, until=5.0)
    poses.add(pose(1.0, x=-1.0))  # older than the newest by more than the span: a replayed bag's start
    assert poses.restarts == 1 and len(poses) == 1 and poses.newest == pose(1.0, x=-1.0)
    poses.add(pose(0.9, x=-2.0))  # late but within the span: in order
    assert poses.restarts == 1 and len(poses) == 2
    poses.add(pose(1.1, x=0.0, frame_id="map"))  # another frame: poses of two frames never mix
    assert poses.restarts == 2 and len(poses) == 1 and poses.at(1.1).pose.frame_id == "map"  # type: ignore[union-attr]


def test_wait_returns_the_pose_once_the_stream_reaches_the_stamp() -> None:
    poses = buffer(extrapolate_s=0.0)
    driving(poses, until=1.0)
    later = threading.Timer(0.05, lambda: poses.add(pose(1.2, x=1.2)))
    later.start()
    found = poses.wait(1.1, timeout_s=10.0)  # returns when the pose comes, long before the timeout
    later.join()
    assert found.reason is None and found.pose is not None and found.pose.x == pytest.approx(1.1)


def test_wait_gives_up_after_its_timeout() -> None:
    poses = buffer(extrapolate_s=0.0)
    driving(poses, until=1.0)
    assert poses.wait(2.0, timeout_s=0.01).reason == AFTER_POSES
    assert poses.wait(0.5, timeout_s=0.0).reason is None


def test_the_streams_clock_is_its_smallest_delay() -> None:
    poses = buffer()
    assert poses.offset_s is None
    poses.add(pose(1.0), received_at=101.3)
    poses.add(pose(1.1), received_at=101.2)  # the fastest: offset 100.1
    poses.add(pose(1.2))  # receipt unknown: does not count
    assert poses.offset_s == pytest.approx(100.1)


def test_pose_buffer_settings_at_their_edges() -> None:
    assert PoseBufferSettings().model_dump() == {
        "span_s": 10.0, "max_poses": 2000, "extrapolate_s": 0.1, "wait_s": 0.2, "max_gap_s": 0.5
    }  # fmt: skip
    assert PoseBufferSettings(extrapolate_s=0.0, wait_s=2.0, max_poses=2).wait_s == 2.0
    for bad in ({"span_s": 0}, {"max_poses": 1}, {"extrapolate_s": -0.1}, {"wait_s": 2.01}, {"max_gap_s": 0},
                {"wait": 1}):  # fmt: skip
        with pytest.raises(ValidationError):
            PoseBufferSettings.model_validate(bad)
    grid = GridSettings.model_validate(
        {"source": "c", "intrinsics": {"fx": 1, "fy": 1, "cx": 0, "cy": 0, "width": 2, "height": 2},
         "poses": {"span_s": 3.0}}
    )  # fmt: skip
    assert grid.poses.span_s == 3.0 and grid.poses.wait_s == 0.2
