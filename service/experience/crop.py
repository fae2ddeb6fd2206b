"""The small JPEG an operator question carries: the part of a camera's last image that shows the question's
region (docs/calibration.md, "Asking an operator"). The region's corners and cell centres, in the grid's frame,
are taken back into the robot's base frame (the pose), the camera's optical frame (its mount) and its pixels
(its intrinsics, scaled to the image), and the box around them is cut out and shrunk."""

from __future__ import annotations

import math

import cv2
import numpy as np
from gcdtrav.schemas.images import encode_jpeg
from gcdtrav.schemas.messages import Pose2D
from gcdtrav.service.experience.ask import Crop, Region
from gcdtrav.service.grid.geometry import CameraMount, PinholeCamera
from numpy.typing import NDArray

CROP_MAX_SIDE = 160  # pixels: a thumbnail for a status line or a phone, not a picture to study
CROP_MARGIN = 8  # pixels around the region's box
CROP_QUALITY = 80
REGION_SAMPLES = 5  # points per side of the region projected (a grid of them: the box holds its whole footprint)


def region_pixels(
    region: Region, pose: Pose2D | None, mount: CameraMount, camera: PinholeCamera
) -> NDArray[np.float64]:
    """(N, 2) pixel coordinates (u right, v down) of sample points of the region in front of the camera."""
    x0, y0, x1, y1 = region
    xs, ys = np.meshgrid(np.linspace(x0, x1, REGION_SAMPLES), np.linspace(y0, y1, REGION_SAMPLES))
    points = np.stack([xs.ravel(), ys.ravel()], axis=1)
    if pose is not None:  # the grid's frame -> the robot's base frame
        c, s = math.cos(pose.yaw), math.sin(pose.yaw)
        points = (points - np.array([pose.x, pose.y])) @ np.array([[c, -s], [s, c]])
    base = np.concatenate([points, np.zeros((len(points), 1))], axis=1)
    optical = (base - mount.origin) @ mount.rotation_optical  # R^T (p - o), row-wise
    ahead = optical[:, 2] > 1e-6
    optical = optical[ahead]
    u = camera.fx * optical[:, 0] / optical[:, 2] + camera.cx
    v = camera.fy * optical[:, 1] / optical[:, 2] + camera.cy
    return np.stack([u, v], axis=1)


def crop_region(
    image: NDArray[np.uint8], region: Region, pose: Pose2D | None, mount: CameraMount, camera: PinholeCamera
) -> bytes | None:
    """A JPEG of the image around the region (camera: intrinsics at the camera's own size); None when the
    region is not in the image."""
    height, width = image.shape[:2]
    sx, sy = width / camera.width, height / camera.height
    scaled = PinholeCamera(camera.fx * sx, camera.fy * sy, camera.cx * sx, camera.cy * sy, width, height)
    pixels = region_pixels(region, pose, mount, scaled)
    if len(pixels) == 0:
        return None
    left, top = np.floor(pixels.min(axis=0)).astype(int) - CROP_MARGIN
    right, bottom = np.ceil(pixels.max(axis=0)).astype(int) + CROP_MARGIN
    left, top, right, bottom = max(left, 0), max(top, 0), min(right, width), min(bottom, height)
    if right <= left or bottom <= top:
        return None
    cut = image[top:bottom, left:right]
    scale = min(1.0, CROP_MAX_SIDE / max(cut.shape[:2]))
    if scale < 1.0:
        size = (max(1, round(cut.shape[1] * scale)), max(1, round(cut.shape[0] * scale)))
        cut = np.asarray(cv2.resize(cut, size, interpolation=cv2.INTER_AREA), np.uint8)
    return encode_jpeg(np.ascontiguousarray(cut), CROP_QUALITY)


def image_crop(
    image: NDArray[np.uint8] | None, pose: Pose2D | None, mount: CameraMount, camera: PinholeCamera | None
) -> Crop | None:
    """The crop callable a question takes, for one camera's last image; None without an image or intrinsics."""
    if image is None or camera is None:
        return None
    return lambda region: crop_region(image, region, pose, mount, camera)
