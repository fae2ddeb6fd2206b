"""Pinhole cameras on a robot: pixels to ground points in the robot's base frame.

Frames (see docs/grid.md): the base frame is x forward, y left, z up, with the ground at z = 0. The camera's
pose in the base frame is given for its body frame (same axes as the base); its optical frame (the image's)
is x right, y down, z forward, as in ROS.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from gcdtrav.schemas.settings.grids import OPTICAL_TO_BODY, rotation_rpy
from numpy.typing import NDArray


@dataclass(frozen=True)
class PinholeCamera:
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def rays(self, u: NDArray[np.floating], v: NDArray[np.floating]) -> NDArray[np.float64]:
        """(N, 3) optical-frame directions (z = 1) through pixel coordinates (u right, v down)."""
        return np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones_like(u, dtype=np.float64)], axis=1)


@dataclass(frozen=True)
class CameraMount:
    """The camera body frame's pose in the base frame: translation (m) and roll, pitch, yaw (rad)."""

    x: float = 0.0
    y: float = 0.0
    z: float = 1.0
    roll: float = 0.0
    pitch: float = 0.0
    yaw: float = 0.0

    @property
    def rotation_optical(self) -> NDArray[np.float64]:
        """Rotation from the optical frame to the base frame."""
        return rotation_rpy(self.roll, self.pitch, self.yaw) @ OPTICAL_TO_BODY

    @property
    def origin(self) -> NDArray[np.float64]:
        return np.array([self.x, self.y, self.z])


def ground_points(
    camera: PinholeCamera, mount: CameraMount, u: NDArray[np.floating], v: NDArray[np.floating], max_range: float
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Where each pixel's ray meets the ground plane z = 0 of the base frame.

    Returns (N, 2) ground points (x, y) and a mask of the pixels that hit the ground: rays at or above the
    horizon never do, and points farther than ``max_range`` (horizontally, from the camera) are left out.
    """
    directions = camera.rays(u, v) @ mount.rotation_optical.T
    origin = mount.origin
    down = directions[:, 2] < -1e-9
    scale = np.where(down, -origin[2] / np.where(down, directions[:, 2], -1.0), np.nan)
    points = origin[None, :2] + scale[:, None] * directions[:, :2]
    distance = np.hypot(points[:, 0] - origin[0], points[:, 1] - origin[1])
    valid = down & (scale > 0) & (distance <= max_range)
    return np.where(valid[:, None], points, np.nan), valid


def depth_points(
    camera: PinholeCamera,
    mount: CameraMount,
    u: NDArray[np.floating],
    v: NDArray[np.floating],
    depth: NDArray[np.floating],
    max_range: float,
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Pixels placed in 3-D by a depth image (metres along the optical axis); returns their (x, y) in the base
    frame. Missing depth (0, NaN, inf) and points beyond ``max_range`` are left out."""
    rows = np.clip(np.round(v).astype(int), 0, depth.shape[0] - 1)
    cols = np.clip(np.round(u).astype(int), 0, depth.shape[1] - 1)
    z = depth[rows, cols].astype(np.float64)
    valid = np.isfinite(z) & (z > 0)
    optical = camera.rays(u, v) * np.where(valid, z, 0.0)[:, None]
    base = optical @ mount.rotation_optical.T + mount.origin[None, :]
    distance = np.hypot(base[:, 0] - mount.x, base[:, 1] - mount.y)
    valid &= distance <= max_range
    return np.where(valid[:, None], base[:, :2], np.nan), valid


def map_cell_pixels(map_shape: tuple[int, int], image_size: tuple[int, int]) -> tuple[NDArray[np.float64], ...]:
    """Image-pixel centres (u, v) of every map patch, row-major, for a map stretched over the whole image."""
    h, w = map_shape
    width, height = image_size
    v, u = np.meshgrid((np.arange(h) + 0.5) * height / h, (np.arange(w) + 0.5) * width / w, indexing="ij")
    return u.ravel(), v.ravel()


def mount_from_axes(origin: NDArray[np.floating], axes: NDArray[np.floating], optical: bool) -> CameraMount:
    """The mount of a camera frame at ``origin`` whose axes are the columns of ``axes``, both in the base frame
    (a tf base -> camera transform). ``optical``: the frame is z forward, x right, y down (ROS's
    ``*_optical_frame``); else x forward, y left, z up (the mount's own body frame)."""
    body = np.asarray(axes, np.float64) @ OPTICAL_TO_BODY.T if optical else np.asarray(axes, np.float64)
    yaw = float(np.arctan2(body[1, 0], body[0, 0]))
    pitch = float(np.arctan2(-body[2, 0], np.hypot(body[2, 1], body[2, 2])))
    roll = float(np.arctan2(body[2, 1], body[2, 2]))
    x, y, z = (float(value) for value in origin)
    return CameraMount(x, y, z, roll, pitch, yaw)
