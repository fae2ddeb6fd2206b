"""A grid's geometry from tf without a bus: poses and mounts handed over as the tree learns them, at the edges
(tf before /tf_static, a missing link, stamps out of order, bad messages, which frame a camera is)."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("rosbags")

from gcdtrav.schemas.inputs import RejectedInput
from gcdtrav.schemas.messages import Pose2D
from gcdtrav.schemas.settings import GridCamera, GridTfSettings
from gcdtrav.service.grid.geometry import CameraMount
from gcdtrav.service.ros.tf import StampedTransform, Transform
from gcdtrav.service.runtime.grids.tf import GridTf

from tools.ros_fixtures import tf_message_cdr

OPTICAL = (-0.5, 0.5, -0.5, 0.5)  # camera_link (x forward) -> *_optical_frame (z forward, x right, y down)
INTRINSICS = {"fx": 40, "fy": 40, "cx": 32, "cy": 24, "width": 64, "height": 48}


def st(parent: str, child: str, stamp: float, xyz=(0.0, 0.0, 0.0), yaw: float = 0.0, q=None) -> StampedTransform:  # type: ignore[no-untyped-def]
    rotation = q if q is not None else (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))
    return StampedTransform(parent, child, stamp, Transform(tuple(xyz), rotation))


def static_tf(pitch: float = 0.3) -> bytes:
    down = (0.0, math.sin(pitch / 2), 0.0, math.cos(pitch / 2))
    return tf_message_cdr(
        [
            st("base_link", "camera_link", 0.0, (0.2, 0.0, 1.0), q=down),
            st("camera_link", "camera_optical_frame", 0.0, q=OPTICAL),
        ]
    )


class Grid:
    """What GridOutputs receives from the grid's tf."""

    def __init__(self, mount: bool = True, pose: bool = True, **camera: object) -> None:
        self.poses: list[Pose2D] = []
        self.mounts: list[tuple[str, CameraMount, str]] = []
        cameras = [GridCamera.model_validate({"source": "cam", "intrinsics": INTRINSICS} | camera)]
        settings = GridTfSettings(mount=mount, pose=pose)
        self.tf = GridTf("cam", settings, cameras, lambda _, pose: self.poses.append(pose), self._mount)

    def _mount(self, camera: str, mount: CameraMount, origin: str) -> None:
        self.mounts.append((camera, mount, origin))


def test_poses_flow_before_the_static_tree_arrives_and_the_mount_once_it_does() -> None:
    grid = Grid()
    assert grid.tf.waiting["cam"].startswith("its tf frame is not known")  # a bare JPEG camera would stay so
    grid.tf.camera_frame("cam", "camera_optical_frame", "image")
    assert grid.tf.on_message(tf_message_cdr([st("odom", "base_link", 5.0, (1.0, 2.0, 0.0), yaw=0.5)]), False) == []
    assert [(p.stamp, p.x, p.y, p.frame_id) for p in grid.poses] == [(5.0, 1.0, 2.0, "odom")]
    assert grid.poses[0].yaw == pytest.approx(0.5)
    assert grid.mounts == [] and grid.tf.waiting["cam"].startswith("tf_unknown_frame")
    grid.tf.on_message(static_tf(), static=True)
    [(camera, mount, origin)] = grid.mounts
    assert (camera, origin) == ("cam", "tf") and "cam" not in grid.tf.waiting
    assert (mount.x, mount.y, mount.z, mount.roll, mount.pitch, mount.yaw) == pytest.approx(
        (0.2, 0.0, 1.0, 0.0, 0.3, 0.0), abs=1e-9
    )
    grid.tf.on_message(static_tf(), static=True)  # latched again (a late subscriber's history): no change
    grid.tf.on_message(tf_message_cdr([st("odom", "base_link", 5.1)]), False)
    assert len(grid.mounts) == 1 and len(grid.poses) == 2
    grid.tf.on_message(static_tf(pitch=0.4), static=True)  # re-calibrated: the new mount is handed over
    assert len(grid.mounts) == 2 and grid.mounts[1][1].pitch == pytest.approx(0.4)


def test_a_missing_link_holds_the_pose_back_until_it_arrives() -> None:
    grid = Grid(mount=False)
    grid.tf.on_message(tf_message_cdr([st("odom", "base_footprint", 1.0, (3.0, 0.0, 0.0))]), False)
    assert grid.poses == [] and grid.tf.waiting["pose"].startswith("tf_unknown_frame")  # base_link unseen
    grid.tf.on_message(static_tf(), static=True)
    assert grid.poses == [] and grid.tf.waiting["pose"].startswith("tf_no_chain")
    grid.tf.on_message(tf_message_cdr([st("base_footprint", "base_link", 0.0, (0.5, 0.0, 0.1))]), static=True)
    assert [(p.stamp, p.x) for p in grid.poses] == [(1.0, 3.5)] and "pose" not in grid.tf.waiting


def test_poses_out_of_order_are_handed_over_newest_first_only_and_the_tree_keeps_them_all() -> None:
    grid = Grid(mount=False)
    for stamp in (1.0, 3.0, 2.0, 2.5, 4.0):
        grid.tf.on_message(tf_message_cdr([st("odom", "base_link", stamp, (stamp, 0.0, 0.0))]), False)
    assert [p.stamp for p in grid.poses] == [1.0, 3.0, 4.0]  # never backwards: 2.0 and 2.5 came late
    assert grid.tf.tree.lookup("odom", "base_link", 2.25).translation == pytest.approx((2.25, 0.0, 0.0))


def test_bad_messages_are_refused_with_reasons_and_the_good_transforms_kept() -> None:
    grid = Grid(mount=False)
    with pytest.raises(RejectedInput) as err:
        grid.tf.on_message(b"\x00\x01\x00\x00garbage", False)
    assert err.value.reason == "bad_tf"
    mixed = [
        st("odom", "base_link", 1.0, (1.0, 0.0, 0.0)),
        st("odom", "base_link", 1.5, q=(0.0, 0.0, 0.0, 2.0)),
        st("odom", "odom", 1.5),
    ]
    refused = grid.tf.on_message(tf_message_cdr(mixed), False)
    assert [r.reason for r in refused] == ["tf_denormalized_quaternion", "tf_self_transform"]
    assert [p.stamp for p in grid.poses] == [1.0]
    old = grid.tf.on_message(tf_message_cdr([st("odom", "base_link", 20.0), st("odom", "base_link", 2.0)]), False)
    assert [r.reason for r in old] == ["tf_old_data"]  # 18 s before the newest: past tf2's 10 s buffer
    far = grid.tf.on_message(tf_message_cdr([st("odom", "base_link", 21.0, (1e9, 0.0, 0.0))]), False)
    assert far == [] and grid.poses[-1].stamp == 20.0 and grid.tf.waiting["pose"].startswith("tf_bad_pose")


def test_a_static_pose_chain_is_not_a_pose_stream() -> None:
    grid = Grid(mount=False)
    grid.tf.on_message(tf_message_cdr([st("odom", "base_link", 0.0)]), static=True)
    assert grid.poses == [] and grid.tf.waiting["pose"].startswith("tf_static_pose")


@pytest.mark.parametrize(
    ("configured", "seen", "expected"),
    [
        (None, [("camera_link", "camera_info")], "camera_link"),
        (None, [("camera_link", "camera_info"), ("camera_optical_frame", "image")], "camera_optical_frame"),
        (None, [("camera_optical_frame", "image"), ("camera_link", "camera_info")], "camera_optical_frame"),
        ("camera_link", [("camera_optical_frame", "image")], "camera_link"),
        (None, [("", "image"), ("/camera_link", "camera_info")], "camera_link"),
    ],
)
def test_the_camera_frame_is_configured_else_the_images_else_camera_infos(
    configured: str | None, seen: list[tuple[str, str]], expected: str
) -> None:
    grid = Grid(pose=False, frame_id=configured) if configured else Grid(pose=False)
    grid.tf.on_message(static_tf(), static=True)
    for frame, origin in seen:
        grid.tf.camera_frame("cam", frame, origin)
    assert grid.tf.frames["cam"][0] == expected
    # either frame gives the same mount: camera_link has body axes, the optical frame optical ones
    assert grid.mounts[-1][1].pitch == pytest.approx(0.3) and grid.mounts[-1][1].yaw == pytest.approx(0.0, abs=1e-12)


def test_frame_axes_overrides_the_name() -> None:
    grid = Grid(pose=False, frame_id="camera_optical_frame", frame_axes="body")
    grid.tf.on_message(static_tf(), static=True)
    mount = grid.mounts[-1][1]
    assert (mount.roll, mount.yaw) != pytest.approx((0.0, 0.0))  # optical axes read as body ones: a wrong mount


def test_a_grid_with_tf_fuses_nothing_until_tf_gives_its_mount_and_pose_and_counts_why() -> None:
    from gcdtrav.schemas.anchors import default_anchor_set
    from gcdtrav.schemas.settings import GridSettings
    from gcdtrav.service.runtime.grids import GridOutputs
    from gcdtrav.service.runtime.history import FrameRecord

    config = {"source": "cam", "intrinsics": INTRINSICS, "tf": {"mount": True, "pose": True}, "poses": {"wait_s": 0}}
    anchors = default_anchor_set()
    grids = GridOutputs([GridSettings.model_validate(config)], len(anchors), "test")
    weights = np.full((len(anchors), 6, 8), 1 / len(anchors), np.float32)

    def frame(stamp: float) -> object:
        record = FrameRecord(0, stamp, "camera_optical_frame", weights.astype(np.float16), anchors, (64, 48))
        return grids.fuse("cam", record, weights)

    grid = grids.sources["cam"]
    assert frame(1.0) is None and grid.health.not_fused == {"no_mount": 1}  # nothing from tf yet
    grids.tf["cam"].on_message(static_tf(), static=True)
    assert frame(1.0) is None and grid.health.not_fused["no_pose"] == 1  # the mount, but no pose: not base_link
    for stamp in (0.9, 1.1):
        grids.tf["cam"].on_message(tf_message_cdr([st("odom", "base_link", stamp, (stamp, 0.0, 0.0))]), False)
    assert frame(1.0) is not None and grid.health.fused == 1 and grid.frame_id() == "odom"
    assert grid.fused_at is not None and grid.fused_at.pose is not None and grid.fused_at.pose.x == pytest.approx(1.0)
