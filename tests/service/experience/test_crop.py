"""A question's crop: the region taken back into the camera's image through the pose, mount and intrinsics."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from gcdtrav.schemas.messages import Pose2D
from gcdtrav.service.experience.crop import CROP_MAX_SIDE, crop_region, image_crop, region_pixels
from gcdtrav.service.grid.geometry import CameraMount, PinholeCamera, ground_points

CAMERA = PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480)
MOUNT = CameraMount(x=0.3, z=1.2, pitch=0.35)


@pytest.mark.parametrize("pose", [None, Pose2D(stamp=0, x=10.0, y=-4.0, yaw=2.0)])
def test_a_ground_point_goes_back_to_the_pixel_it_came_from(pose: Pose2D | None) -> None:
    u, v = np.array([100.0, 320.0, 600.0]), np.array([300.0, 400.0, 470.0])
    base, valid = ground_points(CAMERA, MOUNT, u, v, 50.0)
    assert valid.all()
    for k in range(3):
        x, y = base[k]
        if pose is not None:  # base -> the grid's frame
            c, s = math.cos(pose.yaw), math.sin(pose.yaw)
            x, y = pose.x + c * x - s * y, pose.y + s * x + c * y
        pixels = region_pixels((x, y, x, y), pose, MOUNT, CAMERA)
        assert pixels == pytest.approx(np.tile([u[k], v[k]], (len(pixels), 1)), abs=1e-6)


def test_the_crop_shows_the_region_ahead_and_nothing_behind() -> None:
    image = np.zeros((480, 640, 3), np.uint8)
    image[300:, :320] = (0, 200, 0)  # green ground at the lower left
    pose = Pose2D(stamp=0, x=5.0, y=5.0, yaw=math.pi / 2)  # facing +y: the robot's left is -x
    base, _ = ground_points(CAMERA, MOUNT, np.array([160.0]), np.array([400.0]), 50.0)
    ahead_x, ahead_y = 5.0 - base[0, 1], 5.0 + base[0, 0]
    jpeg = crop_region(image, (ahead_x - 0.1, ahead_y - 0.1, ahead_x + 0.1, ahead_y + 0.1), pose, MOUNT, CAMERA)
    assert jpeg is not None
    crop = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1]
    assert max(crop.shape[:2]) <= CROP_MAX_SIDE and np.median(crop[:, :, 1]) > 150  # green
    behind = (4.8, 2.0, 5.2, 3.0)
    assert crop_region(image, behind, pose, MOUNT, CAMERA) is None
    small = cv2.resize(image, (320, 240))  # the image smaller than the camera's size: intrinsics scale
    assert crop_region(small, (ahead_x - 0.1, ahead_y - 0.1, ahead_x + 0.1, ahead_y + 0.1), pose, MOUNT, CAMERA)
    assert image_crop(None, pose, MOUNT, CAMERA) is None and image_crop(image, pose, MOUNT, None) is None
