"""When a frame is reused instead of inferred: the edges of ReuseTracker's verdicts, on a fake clock."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from fakes import Clock
from gcdtrav.schemas.images import decode_image
from gcdtrav.schemas.messages import Pose2D
from gcdtrav.schemas.settings.share import ReuseSettings, ScheduleSettings
from gcdtrav.service.runtime.frames import PendingFrame
from gcdtrav.service.runtime.grids import GridOutputs
from gcdtrav.service.runtime.schedule.share import Claim, FrameClass, Need
from gcdtrav.service.runtime.triage.change import glance
from gcdtrav.service.runtime.triage.reuse import (
    ANCHORS,
    CHANGED,
    FIRST,
    MAX_REUSE,
    OFF,
    POSE,
    UNCHANGED,
    ReuseTracker,
    Verdict,
)
from scenes import flicker, jpeg_frame, noisy, scene, with_person

from benchmarks.placement import CAMERA, grid_settings, scene_camera

LIMITS = (20_000_000, 40_000_000)


class Robot:
    """One source's frames through a tracker: judge each, and 'infer' those not reused."""

    def __init__(self, settings: ReuseSettings | None = None, with_pose: bool = False) -> None:
        self.clock = Clock(1000.0)
        self.pose: Pose2D | None = Pose2D(stamp=0.0, x=0.0, y=0.0, yaw=0.0) if with_pose else None
        self.anchors = "v1"
        self.tracker = ReuseTracker(
            settings or ReuseSettings(),
            ScheduleSettings(),
            lambda source, stamp, received_at: self.pose,
            self.clock,
            lambda: self.anchors,
        )
        self.settings = self.tracker.settings

    def frame(self, image: np.ndarray, after_s: float = 0.2, refresh_waiting: bool = False) -> Verdict:
        self.clock.now += after_s
        pending = jpeg_frame(image)
        seen = glance(pending, *LIMITS, self.settings.blocks)
        verdict = self.tracker.judge("r1", pending, seen, refresh_waiting)
        if not verdict.reuse:
            self.infer(pending)
        return verdict

    def infer(self, pending: PendingFrame) -> None:
        self.tracker.inferred("r1", pending, decode_image(pending.payload), self.anchors)


def test_the_first_frame_is_inferred_then_the_same_view_is_reused() -> None:
    robot, view = Robot(), scene()
    assert robot.frame(view).reason == FIRST
    verdict = robot.frame(noisy(view, 6.0, 1))
    assert verdict.reuse and verdict.reason == UNCHANGED and not verdict.urgent


def test_noise_and_flicker_only_are_reused_for_up_to_max_reuse_s() -> None:
    robot, view = Robot(ReuseSettings(max_reuse_s=2.0)), scene()
    robot.frame(view)
    reasons = [robot.frame(flicker(noisy(view, 6.0, k), 1 + 0.05 * (k % 3), 3 * (k % 2))).reason for k in range(12)]
    # 0.2 s apart: reused until the reference is 2 s old, then one refresh, then reused again.
    assert reasons == [UNCHANGED] * 9 + [MAX_REUSE] + [UNCHANGED] * 2


def test_max_reuse_s_reached_with_a_refresh_already_waiting_keeps_answering_with_the_last_maps() -> None:
    robot, view = Robot(ReuseSettings(max_reuse_s=1.0)), scene()
    robot.frame(view)
    robot.clock.now += 1.0
    assert robot.frame(view, refresh_waiting=True).reuse
    robot.clock.now += ScheduleSettings().max_wait_s + 0.5  # the refresh yielded up to the floor and beyond
    assert robot.frame(view, refresh_waiting=True).reuse
    robot.clock.now += ScheduleSettings().max_wait_s  # twice the floor: a hung worker
    assert robot.frame(view, refresh_waiting=True).reason == MAX_REUSE


def test_a_person_walking_in_is_inferred_at_the_next_frame_and_is_urgent_after_reuse() -> None:
    robot, view = Robot(), scene()
    robot.frame(view)
    robot.frame(view)  # reused: the source's consumers hold reused maps
    verdict = robot.frame(with_person(view))
    assert not verdict.reuse and verdict.reason == CHANGED and verdict.urgent
    assert robot.frame(with_person(view)).reason == UNCHANGED  # the new reference has the person


def test_a_change_right_after_an_inference_is_not_urgent() -> None:
    robot, view = Robot(), scene()
    robot.frame(view)
    verdict = robot.frame(with_person(view))
    assert verdict.reason == CHANGED and not verdict.urgent


def test_a_change_right_after_a_refresh_of_a_settled_view_is_urgent() -> None:
    """A parked robot's refresh is an inference too, but its view had settled: a person walking in on the very
    next frame is as urgent as after a reuse (else it waits for the parked robot's small share)."""
    robot, view = Robot(ReuseSettings(max_reuse_s=1.0)), scene()
    robot.frame(view)
    reasons = [robot.frame(noisy(view, 6.0, k)).reason for k in range(5)]
    assert reasons == [UNCHANGED] * 4 + [MAX_REUSE]  # the refresh was inferred: the new reference
    verdict = robot.frame(with_person(view))
    assert verdict.reason == CHANGED and verdict.urgent


def test_a_moving_view_is_never_urgent() -> None:
    robot, view = Robot(), scene()
    robot.frame(view)
    verdicts = [robot.frame(np.roll(view, 24 * (k + 1), axis=1)) for k in range(4)]  # a pan: every frame changed
    assert [v.reason for v in verdicts] == [CHANGED] * 4 and not any(v.urgent for v in verdicts)


def test_turning_in_place_before_a_blank_wall_is_a_change() -> None:
    robot, wall = Robot(with_pose=True), np.full((480, 640, 3), 128, np.uint8)
    robot.frame(wall)
    assert robot.frame(wall).reason == UNCHANGED
    robot.pose = Pose2D(stamp=1.0, x=0.0, y=0.0, yaw=math.radians(10))
    assert robot.frame(wall).reason == POSE
    assert robot.frame(wall).reason == UNCHANGED  # the new reference has the new heading


def test_a_pose_that_appears_after_the_reference_is_a_change() -> None:
    robot, view = Robot(), scene()
    robot.frame(view)
    robot.pose = Pose2D(stamp=1.0, x=2.0, y=0.0, yaw=0.0)
    assert robot.frame(view).reason == POSE
    assert robot.frame(view).reason == UNCHANGED


def test_a_robot_that_parked_while_its_frame_was_in_flight_moved_since_that_frame() -> None:
    """The poses compared are where the robot was when each frame was taken (the grid's pose buffer), not the
    newest when the frame reaches the service: the reference, taken while driving, arrives once the robot has
    parked 0.5 m further on; the next frame, taken parked, of a blank wall that looks the same, is a change."""
    grids = GridOutputs([grid_settings(scene_camera())], 8, "test")
    for k in range(101):  # 1 m/s for 1 s, then parked at x = 1: poses at 50 Hz up to 2 s
        grids.add_pose(CAMERA, Pose2D(stamp=k / 50, frame_id="odom", x=min(k / 50, 1.0), y=0.0, yaw=0.0))
    tracker, wall = ReuseTracker(ReuseSettings(), pose_of=grids.reuse_pose), np.full((480, 640, 3), 128, np.uint8)

    def judged(stamp: float) -> Verdict:
        pending = replace(jpeg_frame(wall, CAMERA), stamp=stamp)
        verdict = tracker.judge(CAMERA, pending, glance(pending, *LIMITS, tracker.settings.blocks))
        if not verdict.reuse:
            tracker.inferred(CAMERA, pending, wall)
        return verdict

    assert judged(0.5).reason == FIRST  # taken at x = 0.5, inferred with the robot parked at x = 1
    assert judged(1.5).reason == POSE  # taken at x = 1: the newest poses alike (both x = 1) would reuse it
    assert judged(1.9).reason == UNCHANGED  # parked since
    # A frame the pose stream has not reached yet (or older than its poses): the newest pose, for reuse only.
    assert grids.reuse_pose(CAMERA, 5.0, 0.0) == grids.sources[CAMERA].pose
    assert grids.pose_at(CAMERA, 5.0, 0.0).at.pose is None  # type: ignore[union-attr]
    assert grids.reuse_pose(CAMERA, 0.5, 0.0) == Pose2D(stamp=0.5, frame_id="odom", x=0.5, y=0.0, yaw=0.0)
    assert grids.reuse_pose("another/camera", 0.5, 0.0) is None


def test_reuse_off_infers_every_frame() -> None:
    robot, view = Robot(ReuseSettings(enabled=False)), scene()
    reasons = [robot.frame(view).reason for _ in range(4)]
    assert reasons == [FIRST, OFF, OFF, OFF]


def test_motion_follows_the_view_or_the_pose() -> None:
    still, moving = Robot(), Robot()
    for k in range(10):
        still.frame(noisy(scene(), 5.0, k))
        moving.frame(scene(shift=8 * k))
    assert still.tracker.need("r1").motion == 0.0
    assert moving.tracker.need("r1").motion > 0.5
    driving = Robot(with_pose=True)
    for k in range(10):
        driving.pose = Pose2D(stamp=0.2 * (k + 1), x=0.1 * (k + 1), y=0.0, yaw=0.0)  # 0.5 m/s
        driving.frame(scene())
    assert driving.tracker.need("r1").motion > 0.5  # from the pose, though the view never changes
    assert driving.frame(scene()).need == driving.tracker.need("r1")  # the verdict carries the need


def test_the_verdict_s_claim_is_the_frame_s_class_and_the_source_s_need() -> None:
    """What the scheduler reads from the frame: reused (no claim), refresh, urgent or news, and the need with
    the ambiguity ahead of the last inferred maps."""
    robot, view = Robot(ReuseSettings(max_reuse_s=1.0)), scene()
    assert robot.frame(view).claim == Claim(FrameClass.NEWS, Need(0.0, 0.0))
    robot.tracker.inferred("r1", jpeg_frame(view), view, robot.anchors, ambiguity=0.4)
    assert robot.frame(view).claim is None  # reused
    assert [robot.frame(noisy(view, 6.0, k)).reason for k in range(4)] == [UNCHANGED] * 3 + [MAX_REUSE]
    refresh = robot.frame(view, after_s=1.1)
    assert refresh.reason == MAX_REUSE and refresh.claim == Claim(FrameClass.REFRESH, Need(0.0, 0.0))
    robot.tracker.inferred("r1", jpeg_frame(view), view, robot.anchors, ambiguity=0.4)
    urgent = robot.frame(with_person(view))
    assert urgent.claim is not None and urgent.claim.kind is FrameClass.URGENT
    assert urgent.claim.need.ambiguity == 0.4 and urgent.claim.need.motion > 0
    assert robot.frame(np.roll(view, 24, axis=1)).claim.kind is FrameClass.NEWS  # type: ignore[union-attr]


def test_forget_starts_the_source_again() -> None:
    robot, view = Robot(), scene()
    robot.frame(view)
    robot.tracker.forget("r1")
    assert robot.frame(view).reason == FIRST


def test_an_anchor_swap_infers_the_next_frame_of_an_unchanged_view() -> None:
    robot, view = Robot(), scene()
    robot.frame(view)
    robot.anchors = "v2"
    assert robot.frame(view).reason == ANCHORS
    assert robot.frame(view).reason == UNCHANGED
