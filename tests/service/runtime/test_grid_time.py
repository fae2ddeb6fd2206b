"""Frames fused at the robot's pose when they were taken (issue 40): placement while driving, the edges of the
pose lookup in the grid (reasons counted, the status's why), the mount and intrinsics origins."""

from __future__ import annotations

import math
import threading
from dataclasses import replace

import numpy as np
import pytest
from gcdtrav.client.commands.grid_status import grid_lines
from gcdtrav.schemas.messages import Pose2D, ServiceStatus
from gcdtrav.schemas.settings.share import ReuseSettings
from gcdtrav.service.grid.geometry import CameraMount
from gcdtrav.service.runtime.grids import GridOutputs
from gcdtrav.service.runtime.grids.health import QUIET_S
from gcdtrav.service.runtime.grids.outputs import AfterFusion
from gcdtrav.service.runtime.history import FrameRecord
from gcdtrav.service.runtime.triage.change import glance
from gcdtrav.service.runtime.triage.reuse import ReuseTracker
from scenes import jpeg_frame

from benchmarks.placement import (
    CAMERA,
    drive,
    grid_settings,
    hazard_cells,
    hazard_view,
    place,
    scene_camera,
    unicycle,
)
from tools.loopback import grid_update
from tools.synthetic_scene import Hazard, start_anchors

ANCHORS = start_anchors()
HAZARD = Hazard(4.0, 0.0)


def near_edge_and_centroid(path: object, latency: float, at_capture: bool) -> tuple[float, float]:
    """One frame captured at t = 0 from the origin, fused ``latency`` later: the hazard's nearest cell and its
    centroid along x."""
    grid = drive(path, HAZARD, [latency], at_capture)  # type: ignore[arg-type]
    x, _ = hazard_cells(grid)
    return float(x.min()), float(x.mean())


def test_at_1_mps_and_0_8_s_to_fusion_a_boundary_lands_where_a_standing_robots_grid_puts_it() -> None:
    standing = near_edge_and_centroid(unicycle(0.0, 0.0), 0.8, at_capture=True)
    moving = near_edge_and_centroid(unicycle(1.0, 0.0), 0.8, at_capture=True)
    assert abs(moving[0] - standing[0]) <= 0.3 and abs(moving[1] - standing[1]) <= 0.3
    before = near_edge_and_centroid(unicycle(1.0, 0.0), 0.8, at_capture=False)  # the latest pose, as before
    assert before[0] - standing[0] == pytest.approx(0.8, abs=0.1)  # speed x latency too far ahead


@pytest.mark.parametrize(("speed", "turn_rate"), [(2.0, 0.0), (2.0, 0.5), (1.0, 0.5)])
def test_the_placement_benchmark_keeps_the_hazards_centroid_within_one_and_a_half_cells(
    speed: float, turn_rate: float
) -> None:
    after = place(speed, turn_rate, at_capture=True, seed=0)
    assert after.centroid_error_cells <= 1.5 and after.area_m2 == pytest.approx(1.0, abs=0.2)
    assert place(speed, turn_rate, at_capture=False, seed=0).centroid_error_cells > 5  # the latest pose's


# ---- the edges, in the grid ----------------------------------------------------------------------------


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def outputs(
    clock: Clock, clock_mode: str = "estimated", after_fusion: AfterFusion | None = None, **poses: float
) -> GridOutputs:
    config = grid_settings(scene_camera()).model_copy(update={})
    config = type(config).model_validate(config.model_dump() | {"poses": {"wait_s": 0.0, **poses}})
    return GridOutputs([config], len(ANCHORS), "test", clock=clock, clock_mode=clock_mode, after_fusion=after_fusion)


def frame(stamp: float, pose: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> tuple[FrameRecord, np.ndarray]:
    scene = scene_camera()
    weights = hazard_view(scene, HAZARD, pose, ANCHORS.concepts).astype(np.float16)
    return FrameRecord(0, stamp, "", weights, ANCHORS, (scene.camera.width, scene.camera.height)), weights


def fuse(grids: GridOutputs, stamp: float, unstamped: bool = False) -> bool:
    record, weights = frame(stamp)
    return grids.fuse(CAMERA, record, weights, unstamped=unstamped) is not None


def add_poses(grids: GridOutputs, start: float, stop: float, speed: float = 1.0, hz: float = 50.0) -> None:
    for k in range(round((stop - start) * hz) + 1):
        t = start + k / hz
        grids.add_pose(CAMERA, Pose2D(stamp=t, x=speed * t, y=0.0, yaw=0.0))


def status(grids: GridOutputs, offsets: dict[str, float] | None = None):  # type: ignore[no-untyped-def]
    return grids.statuses(offsets or {})[0]


def test_the_header_carries_the_capture_stamp_and_the_pose_it_was_fused_at() -> None:
    clock = Clock()
    grids = outputs(clock)
    add_poses(grids, 0.0, 2.0)
    record, weights = frame(1.01)
    update = grid_update(grids, CAMERA, record, weights)
    assert update is not None
    header = update.message.header
    assert header.capture_stamp == 1.01 and header.capture_pose == pytest.approx((1.01, 0.0, 0.0))
    assert header.robot == pytest.approx((2.0, 0.0, 0.0))  # the newest pose
    s = status(grids)
    assert s.fused == 1 and s.newest_fused_stamp == 1.01 and s.not_fused_by_reason == {} and s.problem == ""


def test_frames_without_a_pose_are_not_fused_and_counted_by_reason() -> None:
    clock = Clock()
    grids = outputs(clock, extrapolate_s=0.1, span_s=6.0, max_gap_s=0.5)
    assert not fuse(grids, 1.0)  # nothing on the pose stream yet
    add_poses(grids, 3.0, 5.0)
    assert not fuse(grids, 2.85)  # older than the buffer (its oldest pose is 3.0)
    assert not fuse(grids, 5.5)  # newer than the last pose, beyond the extrapolation: the stream lags or stopped
    grids.add_pose(CAMERA, Pose2D(stamp=8.0, x=8.0, y=0.0, yaw=0.0))  # resumed after 3 s
    assert not fuse(grids, 6.0)  # taken while it was silent
    assert fuse(grids, 5.05)  # extrapolated: 0.05 s after the last pose before the gap
    s = status(grids)
    assert s.not_fused_by_reason == {"no_pose": 1, "before_poses": 1, "pose_too_old": 1, "pose_gap": 1}
    assert s.fused == 1 and s.cameras[CAMERA].not_fused == "" and s.poses_held > 0


def test_a_grid_that_fuses_nothing_says_why_in_the_status_and_gcdtrav_status_names_it() -> None:
    clock = Clock()
    grids = outputs(clock)
    add_poses(grids, 0.0, 1.0)
    assert fuse(grids, 0.5)
    clock.now += 1.0
    assert not fuse(grids, 10.0)  # the pose stream stopped at 1.0
    assert status(grids).problem == ""  # fused a second ago
    clock.now += QUIET_S
    assert not fuse(grids, 20.0)
    s = status(grids)
    assert s.problem.startswith(f"fused no frame for {QUIET_S + 1:.0f} s: the pose stream lags or stopped")
    assert s.cameras[CAMERA].not_fused == "pose_too_old" and s.pose_age_s == pytest.approx(QUIET_S + 1)
    table = "\n".join(grid_lines([ServiceStatus.model_construct(instance="box", grids=[s])]))
    assert "why a grid fuses nothing:" in table and f"{CAMERA} (box): fused no frame for" in table
    assert f"{CAMERA} (box): pose_too_old 2" in table


def test_a_grid_waiting_for_camera_info_says_so() -> None:
    clock = Clock()
    config = grid_settings(scene_camera())
    config = type(config).model_validate(
        config.model_dump() | {"intrinsics": None, "camera_info_key": "robot/cam/info", "pose_key": None}
    )
    grids = GridOutputs([config], len(ANCHORS), "test", clock=clock)
    assert not fuse(grids, 1.0)
    s = status(grids)
    assert s.not_fused_by_reason == {"no_intrinsics": 1} and s.cameras[CAMERA].intrinsics is None
    assert "no intrinsics" in s.problem and s.frame_id == "base_link"
    assert "intrinsics MISSING" in "\n".join(grid_lines([ServiceStatus.model_construct(instance="b", grids=[s])]))


def test_fusion_waits_for_a_lagging_pose_stream_without_holding_the_grids_lock() -> None:
    clock = Clock()
    grids = outputs(clock, wait_s=2.0, extrapolate_s=0.0)
    add_poses(grids, 0.0, 1.0)
    grid = grids.sources[CAMERA]
    waiting = threading.Event()
    real_wait = grid.poses.wait

    def wait(stamp: float, timeout_s: float):  # type: ignore[no-untyped-def]
        waiting.set()
        return real_wait(stamp, timeout_s)

    grid.poses.wait = wait  # type: ignore[method-assign]
    fused: list[bool] = []
    worker = threading.Thread(target=lambda: fused.append(fuse(grids, 1.5)))  # the stream has not reached 1.5
    worker.start()
    assert waiting.wait(30)  # it is about to wait (a pose a moment early still fuses the frame)
    # Holding the grid's lock, the stream catches up: a worker that waited under that lock would time out.
    with grid.lock:
        add_poses(grids, 1.02, 2.0)
    worker.join(timeout=20.0)
    assert fused == [True] and grid.fused_at is not None and grid.fused_at.pose.x == pytest.approx(1.5)  # type: ignore[union-attr]


def test_a_stopped_pose_stream_does_not_stall_fusion() -> None:
    clock = Clock()
    grids = outputs(clock, wait_s=2.0, extrapolate_s=0.0, max_gap_s=0.5)
    add_poses(grids, 0.0, 1.0)
    waits: list[float] = []
    buffer = grids.sources[CAMERA].poses
    real_wait = buffer.wait
    buffer.wait = lambda stamp, timeout_s: waits.append(timeout_s) or real_wait(stamp, 0.0)  # type: ignore[method-assign]
    assert not fuse(grids, 1.5)  # the stream was heard just now: the frame may wait for it
    clock.now += 0.6  # silent for longer than max_gap_s: stopped
    assert not fuse(grids, 1.6)
    assert waits == [2.0, 0.0]


def test_after_fusion_sees_the_pose_the_image_was_fused_at_not_the_newest() -> None:
    clock = Clock()
    seen: list[tuple[float, float]] = []

    def after(grid, camera, image):  # type: ignore[no-untyped-def]
        seen.append((grid.fused_at.pose.x, grid.pose.x))  # the experience's question crop reads fused_at

    grids = outputs(clock, after_fusion=after)
    add_poses(grids, 0.0, 2.0)
    assert fuse(grids, 1.2)
    assert seen == [pytest.approx((1.2, 2.0))]


def test_an_unstamped_frame_takes_its_receipt_on_the_pose_streams_clock() -> None:
    clock = Clock()
    estimated, synced = outputs(clock), outputs(clock, clock_mode="synced")
    for grids in (estimated, synced):
        for k in range(101):  # the robot's clock is the service's minus 500 s; poses arrive 0.05 s late
            clock.now = 500.05 + k / 50
            grids.add_pose(CAMERA, Pose2D(stamp=k / 50, x=k / 50, y=0.0, yaw=0.0))
    clock.now = 501.55
    assert fuse(estimated, 501.5, unstamped=True)  # a bare image received at 501.5 (service clock)
    at = estimated.sources[CAMERA].fused_at
    assert at is not None and at.pose is not None and at.pose.x == pytest.approx(1.45)  # 501.5 - 500.05
    assert not fuse(synced, 501.5, unstamped=True)  # synced: the receipt is a robot stamp, far past the poses
    assert status(synced).not_fused_by_reason == {"pose_too_old": 1}
    assert status(estimated, {CAMERA: 500.2}).pose_clock_s == pytest.approx(0.15)  # camera vs pose stream


def test_a_bare_images_fusion_and_reuse_use_the_same_pose() -> None:
    """Issue 50: one capture-pose lookup. A bare image (no stamp) received at 501.5 on the service's clock is
    placed by fusion at its receipt less the pose stream's learnt offset (x = 1.45); the reuse compares its view
    by the same pose, not the newest (x = 2, where the robot drove on to)."""
    clock = Clock()
    grids = outputs(clock)
    for k in range(101):  # the robot's clock is the service's minus 500 s; poses arrive 0.05 s late
        clock.now = 500.05 + k / 50
        grids.add_pose(CAMERA, Pose2D(stamp=k / 50, x=k / 50, y=0.0, yaw=0.0))
    clock.now = 501.55
    seen: list[Pose2D | None] = []  # the poses the reuse judged the frame's view by

    def reuse_pose(camera: str, stamp: float | None, received_at: float) -> Pose2D | None:
        seen.append(grids.reuse_pose(camera, stamp, received_at))
        return seen[-1]

    tracker, wall = ReuseTracker(ReuseSettings(), pose_of=reuse_pose), np.full((480, 640, 3), 128, np.uint8)
    bare = replace(jpeg_frame(wall, CAMERA), stamp=None, received_at=501.5)
    tracker.judge(CAMERA, bare, glance(bare, 20_000_000, 40_000_000, tracker.settings.blocks))
    tracker.inferred(CAMERA, bare, wall)
    assert fuse(grids, 501.5, unstamped=True)
    fused_at = grids.sources[CAMERA].fused_at
    assert fused_at is not None and fused_at.pose is not None and fused_at.pose.x == pytest.approx(1.45)
    assert seen == [fused_at.pose, fused_at.pose]  # judged, then the reference set
    assert grids.sources[CAMERA].pose.x == pytest.approx(2.0)  # type: ignore[union-attr]


def test_a_pose_stream_on_another_clock_than_the_cameras_fuses_nothing_and_shows_the_difference() -> None:
    clock = Clock()
    grids = outputs(clock)
    for k in range(101):  # the odometry's clock runs 3 s behind the camera's (the service's here)
        clock.now = 1000.0 + k / 50
        grids.add_pose(CAMERA, Pose2D(stamp=clock.now - 3.0 - 0.01, x=k / 50, y=0.0, yaw=0.0))
    assert not fuse(grids, clock.now - 0.5)  # taken 0.5 s ago by the camera's clock: 2.5 s past the newest pose
    s = status(grids, {CAMERA: 0.5})  # the camera's learnt offset: its frames arrive 0.5 s after capture
    assert s.not_fused_by_reason == {"pose_too_old": 1}
    assert s.pose_clock_s == pytest.approx(-2.51)  # the pose clock minus the camera's, plus the links' difference


def test_set_mount_drops_the_cached_rays_and_the_status_says_where_the_mount_came_from() -> None:
    clock = Clock()
    grids = outputs(clock)
    add_poses(grids, 0.0, 1.0, speed=0.0)
    assert fuse(grids, 0.5)  # the settings' mount's rays, cached
    camera = grids.sources[CAMERA].cameras[CAMERA]
    scene = scene_camera()
    shape, size = (scene.camera.height, scene.camera.width), (scene.camera.width, scene.camera.height)
    before, valid = camera.base_points(shape, size)
    assert status(grids).cameras[CAMERA].mount == "settings"
    grids.set_mount(CAMERA, CameraMount(x=1.0, z=1.0, pitch=0.35), "tf")  # the camera sits 1 m further forward
    after, _ = camera.base_points(shape, size)
    np.testing.assert_allclose(after[valid, 0] - before[valid, 0], 1.0)
    assert fuse(grids, 0.6) and status(grids).cameras[CAMERA].mount == "tf"


def test_math_sanity_of_the_hazard_scene() -> None:
    """The hazard lies in view of a robot at the origin (the tests above rely on it)."""
    x, y = hazard_cells(drive(unicycle(0.0, 0.0), HAZARD, [0.1], True))
    assert len(x) > 50 and abs(float(x.mean()) - HAZARD.x) < 0.1 and abs(float(y.mean())) < 0.1
    assert math.isfinite(float(x.min()))
