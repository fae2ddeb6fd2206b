"""A ground grid's state: its cameras (intrinsics, mount, depth, ROS topic), the robot's recent poses, the
fused grid and its sequence number, how it is doing; fusing one frame into it at the pose of its capture."""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.delay_window import clock_difference
from gcdtrav.schemas.messages import CameraPlacement, GridCameraStatus, GridStatus, Pose2D
from gcdtrav.schemas.settings import GridCamera, GridSettings
from gcdtrav.service.grid.fusion import GridSpec, GroundGrid
from gcdtrav.service.grid.geometry import CameraMount, PinholeCamera, depth_points, ground_points, map_cell_pixels
from gcdtrav.service.grid.poses import PoseAt, PoseBuffer
from gcdtrav.service.ros.cdr import RosTopic
from gcdtrav.service.runtime.errors import QueryError
from gcdtrav.service.runtime.grids.health import GridHealth
from numpy.typing import NDArray


@dataclass
class CameraState:
    """One camera of a grid: intrinsics (configured or from CameraInfo), mount, latest depth, ROS topic."""

    config: GridCamera
    max_range_m: float
    camera: PinholeCamera | None = None
    depth: NDArray[np.float32] | None = None
    ros: RosTopic | None = None  # the topic of its last frame, if a ROS camera

    def __post_init__(self) -> None:
        self.mount = CameraMount(**self.config.mount.model_dump())
        self.mount_origin: str | None = "settings"  # or "tf" (GridOutputs.set_mount); None: waiting for tf
        self.intrinsics_origin: str | None = None  # "settings" or "camera_info"; None: not known yet
        if self.config.intrinsics is not None and self.camera is None:
            self.camera = PinholeCamera(**self.config.intrinsics.model_dump())
            self.intrinsics_origin = "settings"
        self._ground_cache: dict[tuple[Any, ...], tuple[NDArray[np.float64], NDArray[np.bool_]]] = {}

    def set_mount(self, mount: CameraMount, origin: str) -> None:
        """A new mount (from the settings or tf): the cached ground rays were the old mount's."""
        self.mount, self.mount_origin = mount, origin
        self._ground_cache = {}

    def camera_for(self, image_size: tuple[int, int]) -> PinholeCamera:
        """Intrinsics scaled to the incoming image's size."""
        camera = self.camera
        if camera is None:
            raise QueryError(f"no intrinsics for '{self.config.source}' yet (waiting for CameraInfo)")
        sx, sy = image_size[0] / camera.width, image_size[1] / camera.height
        return PinholeCamera(camera.fx * sx, camera.fy * sy, camera.cx * sx, camera.cy * sy, *image_size)

    def base_points(
        self, map_shape: tuple[int, int], image_size: tuple[int, int]
    ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Ground (or depth) points in the base frame of every map patch, and which patches have one."""
        camera = self.camera_for(image_size)
        u, v = map_cell_pixels(map_shape, image_size)
        if self.depth is not None:
            depth = np.asarray(cv2.resize(self.depth, image_size, interpolation=cv2.INTER_NEAREST), np.float32)
            return depth_points(camera, self.mount, u, v, depth, self.max_range_m)
        key = (map_shape, image_size, camera)
        if key not in self._ground_cache:  # a fixed camera: the same rays every frame
            self._ground_cache = {key: ground_points(camera, self.mount, u, v, self.max_range_m)}
        return self._ground_cache[key]


@dataclass
class SourceGrid:
    """One grid, its cameras and the robot's recent poses; published and queried under ``config.source``."""

    config: GridSettings
    grid: GroundGrid
    seq: int = -1
    cameras: dict[str, CameraState] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.lock = threading.Lock()
        self.cameras = {c.source: CameraState(c, self.config.max_range_m) for c in self.config.camera_list()}
        if self.config.tf is not None and self.config.tf.mount:
            for camera in self.cameras.values():
                camera.mount_origin = None  # unknown until tf links the base frame to the camera's frame
        p = self.config.poses
        self.poses = PoseBuffer(p.span_s, p.max_poses, p.extrapolate_s, p.max_gap_s)  # its own lock
        self.health = GridHealth()
        self.tf_waiting: Mapping[str, str] = {}  # with tf: GridTf.waiting, what tf does not give yet and why
        self.fused_at: PoseAt | None = None  # the pose the last fused frame was projected with
        self.fused_stamp: float | None = None  # that frame's capture stamp
        self.speed_mask_at: float | None = None  # service clock of the last speed mask handed out; None: none yet
        self.speed_safe = False  # whether that mask was the safe one (the floor everywhere)

    def speed_mask_due(self, now: float) -> bool:
        """Whether a fusion at ``now`` hands out a new speed mask (at most speed.rate_hz; at once after a safe
        one, which a fresh grid replaces); marks it handed out. Under the lock."""
        speed = self.config.speed
        if speed is None:
            return False
        last = self.speed_mask_at
        if last is not None and not self.speed_safe and now - last < 1.0 / speed.rate_hz:
            return False
        self.speed_mask_at, self.speed_safe = now, False
        return True

    def speed_stale(self, now: float) -> bool:
        """Whether the grid's live mask outlived its evidence: for speed.stale_s no frame fused and no view of its
        cameras found unchanged (a standing robot's frames are reused, not fused, up to reuse.max_reuse_s: its
        grid still holds). Under the lock."""
        speed, health = self.config.speed, self.health
        if speed is None or self.speed_mask_at is None or self.speed_safe:
            return False
        evidence = [at for at in (health.fused_at, health.unchanged_at) if at is not None]
        return not evidence or now - max(evidence) >= speed.stale_s

    @property
    def pose(self) -> Pose2D | None:
        """The robot's newest pose (by stamp); None before the first."""
        return self.poses.newest

    def expects_pose(self) -> bool:
        """Whether frames need a pose to be fused: a pose stream is configured (pose_key or tf.pose), or poses
        came. A grid without one lives in the robot's base frame."""
        from_tf = self.config.tf is not None and self.config.tf.pose
        return self.config.pose_key is not None or from_tf or self.poses.received > 0

    def fuse(
        self,
        camera: CameraState,
        weights: NDArray[np.floating],
        image_size: tuple[int, int],
        stamp: float,
        anchors: AnchorSet,
        match: NDArray[np.floating] | None = None,
        pose: Pose2D | None = None,
    ) -> int:
        """Fuse a frame taken at ``stamp`` from ``pose`` (the robot's then; None: the grid is in the base frame)."""
        points, valid = camera.base_points((weights.shape[1], weights.shape[2]), image_size)
        flat = weights.reshape(weights.shape[0], -1)[:, valid].astype(np.float32)
        scores = None if match is None else np.asarray(match, np.float32).reshape(-1)[valid]
        ground = points[valid]
        if pose is not None:  # into the odometry frame, and keep the robot at the grid's centre
            c, s = math.cos(pose.yaw), math.sin(pose.yaw)
            ground = ground @ np.array([[c, s], [-s, c]]) + np.array([pose.x, pose.y])
            half = self.grid.spec.cells * self.grid.spec.resolution_m / 2
            self.grid.scroll_to((pose.x - half, pose.y - half))
        landed = self.grid.add(ground, flat, stamp, anchors, scores)
        self.seq += 1
        return landed

    def frame_id(self) -> str:
        """The frame the grid is in: the pose's, else the robot's base."""
        return self.pose.frame_id if self.pose is not None else "base_link"

    def ros_topic(self) -> RosTopic | None:
        """The ROS topic the grid's ROS outputs derive from: its first camera (in the configured order) that
        has sent a ROS frame; None if none has."""
        return next((camera.ros for camera in self.cameras.values() if camera.ros is not None), None)


def grid_spec(config: GridSettings) -> GridSpec:
    return GridSpec(config.size_m, config.resolution_m, config.half_life_s, config.max_age_s)


def _ago(now: float, then: float | None) -> float | None:
    return None if then is None else round(now - then, 3)


def grid_status(grid: SourceGrid, now: float, clock_offsets: Mapping[str, float]) -> GridStatus:
    """One grid's status at ``now`` (service clock); ``clock_offsets``: each source's learnt clock. Under the
    grid's lock."""
    health = grid.health
    waiting = dict(grid.tf_waiting)  # a copy: GridTf writes it under its own lock
    cameras = {
        source: GridCameraStatus(
            intrinsics=camera.intrinsics_origin if camera.camera is not None else None,
            mount=camera.mount_origin,
            not_fused=health.last_reason.get(source, ""),
            placement=None if camera.mount_origin is None else _placement(camera.mount),
        )
        for source, camera in grid.cameras.items()
    }
    # The pose stream's clock minus the camera's: both learnt by the one smallest-delay window on the service's
    # clock, from the grid's first camera with a learnt clock (its cameras share the robot's).
    camera_offset = next((clock_offsets[c] for c in grid.cameras if c in clock_offsets), None)
    pose_clock = clock_difference(camera_offset, grid.poses.offset_s)
    return GridStatus(
        source=grid.config.source,
        frame_id=grid.frame_id(),
        fused=health.fused,
        not_fused_by_reason=dict(health.not_fused),
        newest_fused_stamp=health.newest_fused_stamp,
        fused_ago_s=_ago(now, health.fused_at),
        pose_age_s=_ago(now, health.pose_received_at),
        pose_clock_s=None if pose_clock is None else round(pose_clock, 3),
        poses_held=len(grid.poses),
        cameras=cameras,
        costmap_ago_s=_ago(now, health.costmap_at),
        speed_ago_s=_ago(now, grid.speed_mask_at),
        speed_safe=grid.speed_safe if grid.speed_mask_at is not None else None,
        problem=_with_tf(health.problem(now), waiting),
        tf_waiting=waiting,
    )


def _placement(mount: CameraMount) -> CameraPlacement:
    return CameraPlacement(x=mount.x, y=mount.y, z=mount.z, roll=mount.roll, pitch=mount.pitch, yaw=mount.yaw)


def _with_tf(problem: str, waiting: dict[str, str]) -> str:
    """A grid that fuses nothing and waits for tf: the problem names what tf lacks (the missing link)."""
    if not problem or not waiting:
        return problem
    return problem + "; tf: " + "; ".join(f"{what}: {why}" for what, why in sorted(waiting.items()))
