"""A grid's speed outputs in the runtime, on a simulated clock: the mask at most speed.rate_hz, the SpeedLimit with
every fused frame at the robot's pose, the safe mask (the floor everywhere) once a grid goes stale and at stop,
and the status and metrics that show the speed layer's age."""

from __future__ import annotations

import numpy as np
import pytest
from gcdtrav.schemas.messages import Pose2D
from gcdtrav.service.grid import speed
from gcdtrav.service.runtime.grids import GridOutputs
from gcdtrav.service.runtime.grids.encoding import speed_of
from gcdtrav.service.runtime.history import FrameRecord
from gcdtrav.service.runtime.metrics import speed_families

from benchmarks.placement import CAMERA, grid_settings, scene_camera
from tools.synthetic_scene import Hazard, hazard_view, start_anchors

pytest.importorskip("rosbags")

from gcdtrav.service.ros import cdr as ros

ANCHORS = start_anchors()
HAZARD = Hazard(4.0, 0.0)  # water on paved ground, 4 m ahead of the robot at the origin
FLOOR, RATE_HZ, STALE_S = 0.25, 2.0, 3.0


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def speed_grids(clock: Clock, **speed: object) -> GridOutputs:
    config = grid_settings(scene_camera())
    settings = {"floor": FLOOR, "rate_hz": RATE_HZ, "stale_s": STALE_S, **speed}
    config = type(config).model_validate(config.model_dump() | {"speed": settings, "poses": {"wait_s": 0.0}})
    grids = GridOutputs([config], len(ANCHORS), "test", clock=clock)
    grids.add_pose(CAMERA, Pose2D(stamp=0.0, frame_id="odom", x=0.0, y=0.0, yaw=0.0))
    return grids


def fuse(grids: GridOutputs, stamp: float = 0.0):  # type: ignore[no-untyped-def]
    scene = scene_camera()
    weights = hazard_view(scene, HAZARD, (0.0, 0.0, 0.0), ANCHORS.concepts).astype(np.float16)
    record = FrameRecord(0, stamp, "", weights, ANCHORS, (scene.camera.width, scene.camera.height))
    fused = grids.fuse(CAMERA, record, weights)
    assert fused is not None
    return fused.encode()


def mask_of(payload: bytes | None) -> np.ndarray:
    assert payload is not None
    message = ros.typestore().deserialize_cdr(payload, ros.OCCUPANCY_GRID)
    return np.asarray(message.data, np.int8).reshape(message.info.height, message.info.width)


def limit_of(payload: bytes) -> float:
    return float(ros.typestore().deserialize_cdr(payload, ros.SPEED_LIMIT).speed_limit)


def test_the_mask_slows_the_hazard_leaves_paved_ground_free_and_goes_out_at_most_rate_hz() -> None:
    clock = Clock()
    grids = speed_grids(clock)
    first = fuse(grids)
    assert first.speed is not None and first.message.speed_png is not None
    mask = mask_of(first.speed.mask)
    header, floor = first.message.header, round(FLOOR * 100)
    x = header.origin[0] + (np.arange(header.cells) + 0.5) * header.resolution
    y = header.origin[1] + (np.arange(header.cells) + 0.5) * header.resolution
    hazard = HAZARD.covers(*np.meshgrid(x, y))
    seen = first.message.header.known_cells > 0
    assert seen and (mask[hazard] == floor).mean() > 0.9  # water: P(T < tau) ~ 1
    assert set(np.unique(mask)) <= {0, *range(1, 101)}
    assert (mask == 0).sum() > 0  # paved ground seen: no limit
    assert limit_of(first.speed.limit) == floor  # the robot's own cell is not seen (the camera looks ahead)

    clock.now += 0.2  # within 1 / rate_hz: the limit, no mask
    second = fuse(grids)
    assert second.speed is not None and second.speed.mask is None and second.speed.limit
    clock.now += 1 / RATE_HZ
    assert fuse(grids).speed.mask is not None


def test_a_stale_grid_hands_out_the_safe_mask_once_and_a_fresh_frame_replaces_it() -> None:
    clock = Clock()
    grids = speed_grids(clock)
    assert grids.safe_speed(stale_only=True) == [] and grids.safe_speed(stale_only=False) == []  # none out yet
    fuse(grids)
    status = grids.statuses({})[0]
    assert status.speed_ago_s == 0.0 and status.speed_safe is False
    clock.now += STALE_S - 0.01
    assert grids.safe_speed(stale_only=True) == []
    clock.now += 0.01
    (safe,) = grids.safe_speed(stale_only=True)
    assert safe.safe and (mask_of(safe.mask) == round(FLOOR * 100)).all() and limit_of(safe.limit) == FLOOR * 100
    assert grids.safe_speed(stale_only=True) == []  # once
    clock.now += 1.5
    status = grids.statuses({})[0]
    assert status.speed_safe is True and status.speed_ago_s == 1.5
    (metric_age, metric_safe) = speed_families([status])
    assert [s.value for s in metric_age.samples] == [1.5] and [s.value for s in metric_safe.samples] == [1]
    assert metric_age.samples[0].labels == {"source": CAMERA}
    fresh = fuse(grids, 0.0)  # at once, not after 1 / rate_hz: a fresh grid replaces the safe mask
    assert fresh.speed is not None and fresh.speed.mask is not None and not fresh.speed.safe
    assert grids.statuses({})[0].speed_safe is False


def test_a_standing_robots_unchanged_views_keep_its_grid_from_going_stale() -> None:
    """The triage reuses an unchanged view's maps instead of fusing it (up to reuse.max_reuse_s, 5 s, beyond
    stale_s): the camera is alive and its view holds, so the live mask stays."""
    clock = Clock()
    grids = speed_grids(clock)
    fuse(grids)
    for _ in range(3):
        clock.now += STALE_S - 0.5
        grids.unchanged(CAMERA)
        assert grids.safe_speed(stale_only=True) == []
    grids.unchanged("another/camera")  # not a grid's: nothing
    clock.now += STALE_S
    (safe,) = grids.safe_speed(stale_only=True)  # the views stopped too
    assert safe.safe


def test_at_stop_every_live_mask_is_replaced_by_the_safe_one() -> None:
    clock = Clock()
    grids = speed_grids(clock)
    fuse(grids)
    (safe,) = grids.safe_speed(stale_only=False)
    assert safe.safe and safe.frame_id == "odom"
    assert grids.safe_speed(stale_only=False) == []  # already safe


def test_floor_one_leaves_no_limit_even_when_stale() -> None:
    clock = Clock()
    grids = speed_grids(clock, floor=1.0)
    update = fuse(grids)
    assert update.speed is not None and (mask_of(update.speed.mask) == 0).all() and limit_of(update.speed.limit) == 0
    clock.now += STALE_S
    (safe,) = grids.safe_speed(stale_only=True)
    assert (mask_of(safe.mask) == 0).all() and limit_of(safe.limit) == 0.0


def test_a_grid_without_speed_has_no_speed_outputs_status_or_metrics() -> None:
    clock = Clock()
    config = grid_settings(scene_camera())
    grids = GridOutputs([config], len(ANCHORS), "test", clock=clock)
    grids.add_pose(CAMERA, Pose2D(stamp=0.0, frame_id="odom", x=0.0, y=0.0, yaw=0.0))
    update = fuse(grids)
    assert update.speed is None and update.message.speed_png is None
    clock.now += 100
    assert grids.safe_speed(stale_only=True) == [] and grids.safe_speed(stale_only=False) == []
    status = grids.statuses({})[0]
    assert status.speed_ago_s is None and status.speed_safe is None
    assert all(not family.samples for family in speed_families([status]))


def test_the_assembled_runtime_tells_the_grid_of_each_reused_view() -> None:
    """The wiring: the triage's reuse reaches GridOutputs.unchanged through the one hand-off out."""
    import time

    from fakes import assembled
    from gcdtrav.schemas.settings import ServiceSettings
    from scenes import jpeg_frame, noisy, scene

    grid = {
        "source": "r1", "intrinsics": {"fx": 40, "fy": 40, "cx": 32, "cy": 24, "width": 64, "height": 48},
        "mount": {"z": 1.0, "pitch": 0.5}, "size_m": 6.0, "resolution_m": 0.5, "speed": {},
    }  # fmt: skip
    runtime, sink, _ = assembled(ServiceSettings.model_validate({"grids": [grid], "preview": False}))
    assert runtime.grids is not None
    health = runtime.grids.sources["r1"].health
    runtime.worker.start()
    view = scene()
    try:
        for k in range(3):  # the first is inferred and fused, the others reused
            runtime.queue.put("r1", jpeg_frame(noisy(view, 5.0, k), "r1"))
            deadline = time.monotonic() + 60  # a failure's bound
            while len(sink.maps()) <= k and time.monotonic() < deadline:
                time.sleep(0.005)
    finally:
        assert runtime.worker.stop(time.monotonic() + 10)
    assert health.fused == 1 and health.unchanged_at is not None and health.unchanged_at >= health.fused_at


def test_a_grid_that_does_not_know_the_robots_pose_limits_at_the_floor() -> None:
    """header.robot is None until the grid knows where the robot is: the limit is the floor's, not a crash."""
    grids = speed_grids(Clock())
    fused = fuse(grids)
    config = grid_settings(scene_camera())
    config = type(config).model_validate(config.model_dump() | {"speed": {"floor": FLOOR}})
    header = fused.message.header.model_copy(update={"robot": None})
    fractions = np.ones((header.cells, header.cells), np.float32)  # full speed everywhere but where the robot is
    update = speed_of(config, header, fractions, None, True)
    assert limit_of(update.limit) == speed.limit_percent(FLOOR) == round(FLOOR * 100)
