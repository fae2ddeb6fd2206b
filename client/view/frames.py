"""Where things are, for Foxglove's 3D panel: the robot's pose (grid frame, e.g. odom -> base_link) from the
grid's header and the pose its last frame was fused at, each camera's mount (base_link -> its optical frame)
as the grid's status reports it (else the service's settings file, unless they take it from tf), intrinsics from
that settings file, the camera's frustum and a marker of the robot.

Frames as the service uses them (docs/grid.md): base_link is x forward, y left, z up, ground at z = 0; a
camera's mount places its body frame (axes of the base) by x, y, z, roll, pitch, yaw (R = Rz Ry Rx); images
live in its optical frame (x right, y down, z forward), which is the frame the viewer's images, its
CameraCalibration and its transform name.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from foxglove.messages import (
    ArrowPrimitive,
    CameraCalibration,
    Color,
    FrameTransform,
    LinePrimitive,
    LinePrimitiveLineType,
    Point3,
    Pose,
    Quaternion,
    SceneEntity,
    Timestamp,
    Vector3,
)
from gcdtrav.schemas.messages import GridCameraStatus
from gcdtrav.schemas.settings import CameraIntrinsics, CameraMountSettings, load_settings
from gcdtrav.schemas.settings.grids import OPTICAL_TO_BODY, rotation_rpy
from numpy.typing import NDArray

BASE_FRAME = "base_link"
FRUSTUM_DEPTH_M = 2.0  # the frustum's lines end this far along the optical axis
FRUSTUM_COLOUR = Color(r=0.2, g=0.8, b=1.0, a=1.0)
ROBOT_COLOUR = Color(r=1.0, g=1.0, b=1.0, a=1.0)
CAPTURE_COLOUR = Color(r=1.0, g=0.6, b=0.1, a=0.6)  # where the last fused frame was taken from


@dataclass(frozen=True)
class CameraSetup:
    """One camera as the service's settings describe it: where it sits (unless its grid takes the mount from tf),
    and its intrinsics if given (a camera_info_key's intrinsics stay on the robot: no frustum then)."""

    source: str
    mount: CameraMountSettings
    intrinsics: CameraIntrinsics | None
    mount_from_tf: bool = False


def cameras_from_settings(path: Path) -> dict[str, CameraSetup]:
    """Every grid camera of the service's settings file, by source (the same file `gcdtrav serve` reads)."""
    settings = load_settings(path)
    return {
        camera.source: CameraSetup(
            camera.source, camera.mount, camera.intrinsics, grid.tf is not None and grid.tf.mount
        )
        for grid in settings.grids
        for camera in grid.camera_list()
    }


def camera_mount(setup: CameraSetup | None, status: GridCameraStatus | None) -> CameraMountSettings | None:
    """Where to draw a camera: the mount its grid projects with, as the grid's status reports it (from tf or the
    settings); before a status (or from a service before 1.4), the settings file's mount, unless the grid takes
    it from tf. None: not known (tf has not given it yet): the camera is not drawn rather than drawn wrong."""
    if status is not None and status.placement is not None:
        p = status.placement
        return CameraMountSettings(x=p.x, y=p.y, z=p.z, roll=p.roll, pitch=p.pitch, yaw=p.yaw)
    if setup is None or setup.mount_from_tf or (status is not None and status.mount != "settings"):
        return None
    return setup.mount


def camera_frame(source: str, frame_id: str) -> str:
    """The optical frame of a source's images: the frame id the robot gave them, else '{source}/camera'."""
    return frame_id or f"{source}/camera"


def quaternion(rotation: NDArray[np.float64]) -> Quaternion:
    """The unit quaternion of a rotation matrix (Shepperd's method: stable for every rotation)."""
    m = rotation
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0:
        s = 2.0 * math.sqrt(1.0 + trace)
        w, x, y, z = 0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        w, x, y, z = (m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        w, x, y, z = (m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        w, x, y, z = (m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s
    return Quaternion(x=float(x), y=float(y), z=float(z), w=float(w))


def robot_transform(when: Timestamp, grid_frame: str, robot: tuple[float, float, float]) -> FrameTransform:
    """grid frame (e.g. odom) -> base_link, from the grid header's (x, y, yaw)."""
    x, y, yaw = robot
    return FrameTransform(
        timestamp=when,
        parent_frame_id=grid_frame,
        child_frame_id=BASE_FRAME,
        translation=Vector3(x=x, y=y, z=0.0),
        rotation=Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)),
    )


def mount_transform(when: Timestamp, mount: CameraMountSettings, optical_frame: str) -> FrameTransform:
    """base_link -> the camera's optical frame: the mount's rotation, then optical axes to body axes."""
    rotation = rotation_rpy(mount.roll, mount.pitch, mount.yaw) @ OPTICAL_TO_BODY
    return FrameTransform(
        timestamp=when,
        parent_frame_id=BASE_FRAME,
        child_frame_id=optical_frame,
        translation=Vector3(x=mount.x, y=mount.y, z=mount.z),
        rotation=quaternion(rotation),
    )


def calibration(
    when: Timestamp, intrinsics: CameraIntrinsics, optical_frame: str, image_size: tuple[int, int] | None
) -> CameraCalibration:
    """The camera's pinhole model (no distortion) at the image's size (intrinsics scale with it, as in the
    service's projection)."""
    width, height = image_size if image_size and min(image_size) > 0 else (intrinsics.width, intrinsics.height)
    sx, sy = width / intrinsics.width, height / intrinsics.height
    fx, fy, cx, cy = intrinsics.fx * sx, intrinsics.fy * sy, intrinsics.cx * sx, intrinsics.cy * sy
    return CameraCalibration(
        timestamp=when,
        frame_id=optical_frame,
        width=width,
        height=height,
        distortion_model="plumb_bob",
        D=[0.0] * 5,
        K=[fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0],
        R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        P=[fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0],
    )


def frustum_corners(intrinsics: CameraIntrinsics, depth: float = FRUSTUM_DEPTH_M) -> list[tuple[float, float, float]]:
    """The image's four corners at ``depth`` along the optical axis, in the optical frame (clockwise from
    top left)."""
    corners = ((0, 0), (intrinsics.width, 0), (intrinsics.width, intrinsics.height), (0, intrinsics.height))
    return [
        ((u - intrinsics.cx) / intrinsics.fx * depth, (v - intrinsics.cy) / intrinsics.fy * depth, depth)
        for u, v in corners
    ]


def frustum_entity(when: Timestamp, source: str, intrinsics: CameraIntrinsics, optical_frame: str) -> SceneEntity:
    """Lines from the camera to the corners of its image at FRUSTUM_DEPTH_M and around them."""
    corners = [Point3(x=x, y=y, z=z) for x, y, z in frustum_corners(intrinsics)]
    apex = Point3(x=0.0, y=0.0, z=0.0)
    points: list[Point3] = []
    for index, corner in enumerate(corners):
        points += [apex, corner, corner, corners[(index + 1) % 4]]
    line = LinePrimitive(
        type=LinePrimitiveLineType.LineList,
        pose=Pose(position=Vector3(x=0.0, y=0.0, z=0.0), orientation=Quaternion(w=1.0)),
        thickness=2.0,
        scale_invariant=True,
        points=points,
        color=FRUSTUM_COLOUR,
    )
    return SceneEntity(timestamp=when, frame_id=optical_frame, id=f"{source}/frustum", frame_locked=True, lines=[line])


def robot_entity(when: Timestamp, source: str) -> SceneEntity:
    """An arrow at base_link's origin along x: the robot and its heading."""
    arrow = ArrowPrimitive(
        pose=Pose(position=Vector3(x=0.0, y=0.0, z=0.05), orientation=Quaternion(w=1.0)),
        shaft_length=0.45,
        shaft_diameter=0.08,
        head_length=0.2,
        head_diameter=0.2,
        color=ROBOT_COLOUR,
    )
    return SceneEntity(timestamp=when, frame_id=BASE_FRAME, id=f"{source}/robot", frame_locked=True, arrows=[arrow])


def capture_entity(when: Timestamp, source: str, grid_frame: str, pose: tuple[float, float, float]) -> SceneEntity:
    """A faint arrow in the grid frame where the robot was when the last fused frame was taken (GridHeader.
    capture_pose): its distance behind the robot's marker is speed x the frame's latency."""
    x, y, yaw = pose
    arrow = ArrowPrimitive(
        pose=Pose(
            position=Vector3(x=x, y=y, z=0.02),
            orientation=Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)),
        ),
        shaft_length=0.45,
        shaft_diameter=0.05,
        head_length=0.2,
        head_diameter=0.15,
        color=CAPTURE_COLOUR,
    )
    return SceneEntity(timestamp=when, frame_id=grid_frame, id=f"{source}/capture", arrows=[arrow])
