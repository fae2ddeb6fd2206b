"""The grid's tf settings at their edges: geometry from one place only, frames named as tf names them."""

from __future__ import annotations

from typing import Any

import pytest
from gcdtrav.schemas.settings import GridSettings
from gcdtrav.schemas.settings.grids import TF_KEY, TF_STATIC_KEY
from pydantic import ValidationError

INTRINSICS = {"fx": 40, "fy": 40, "cx": 32, "cy": 24, "width": 64, "height": 48}
ONE = {"source": "cam", "intrinsics": INTRINSICS}
TWO: dict[str, Any] = {
    "source": "robot",
    "cameras": [{"source": "front", "intrinsics": INTRINSICS}, {"source": "back", "intrinsics": INTRINSICS}],
}


def grid(**fields: Any) -> GridSettings:
    return GridSettings.model_validate(ONE | fields)


def test_the_defaults_are_tf2s_and_rmw_zenohs() -> None:
    tf = grid(tf={"mount": True}).tf
    assert tf is not None and (tf.base_frame, tf.odom_frame, tf.buffer_s) == ("base_link", "odom", 10.0)
    assert (tf.tf_key, tf.tf_static_key) == (TF_KEY, TF_STATIC_KEY)
    assert TF_KEY == "*/tf/tf2_msgs::msg::dds_::TFMessage_/*" and not tf.pose
    assert grid().tf is None and grid().camera_list()[0].frame_axes == "auto"


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"tf": {"mount": True}, "mount": {"z": 1.5}}, "the mount comes from mount: or from tf"),
        ({"tf": {"mount": True}, "mount": {"pitch": 0.2}}, "the mount comes from mount: or from tf"),
        ({"tf": {"pose": True}, "pose_key": "r/pose"}, "the pose comes from pose_key or from tf"),
        ({"tf": {}}, "set mount, pose or both"),
        ({"tf": {"mount": False, "pose": False}}, "set mount, pose or both"),
        ({"frame_id": "camera_optical_frame"}, "read only with tf: {mount: true}"),
        ({"tf": {"pose": True}, "frame_axes": "optical"}, "read only with tf: {mount: true}"),
        ({"tf": {"pose": True, "odom_frame": "/odom"}}, "not a tf frame id"),
        ({"tf": {"mount": True}, "frame_id": ""}, "not a tf frame id"),
        ({"tf": {"mount": True, "base_frame": "b" * 257}}, "not a tf frame id"),
        ({"tf": {"pose": True, "base_frame": "odom"}}, "base_frame and odom_frame are both 'odom'"),
        ({"tf": {"pose": True, "buffer_s": 0}}, "greater than 0"),
        ({"tf": {"pose": True, "buffer_s": 301}}, "less than or equal to 300"),
        ({"tf": {"pose": True, "tf_prefix": "x"}}, "Extra inputs are not permitted"),
        ({"tf": {"mount": True}, "frame_axes": "sideways"}, "'auto', 'optical' or 'body'"),
    ],
)
def test_geometry_given_twice_or_half_is_an_error(fields: dict[str, Any], message: str) -> None:
    with pytest.raises(ValidationError, match=message.replace("(", r"\(").replace("{", r"\{")):
        grid(**fields)


def test_a_dumped_tf_grid_validates_again_unchanged() -> None:
    config = grid(tf={"mount": True, "pose": True}, frame_id="cam_optical_frame", frame_axes="optical")
    assert GridSettings.model_validate(config.model_dump()) == config


def test_pose_from_tf_and_mounts_typed_are_fine_and_so_is_the_reverse() -> None:
    assert grid(tf={"pose": True}, mount={"z": 1.2, "pitch": 0.3}).tf is not None
    assert grid(tf={"mount": True}, pose_key="r/pose", frame_id="cam_optical_frame").frame_id == "cam_optical_frame"


def test_with_several_cameras_each_names_its_frame_and_none_may_type_a_mount() -> None:
    config = TWO | {"tf": {"mount": True}}
    config["cameras"] = [config["cameras"][0] | {"frame_id": "front_optical_frame"}, config["cameras"][1]]
    cameras = GridSettings.model_validate(config).camera_list()
    assert [c.frame_id for c in cameras] == ["front_optical_frame", None]
    config["cameras"] = [config["cameras"][0], config["cameras"][1] | {"mount": {"z": 0.5}}]
    with pytest.raises(ValidationError, match="camera 'back': the mount comes from mount: or from tf"):
        GridSettings.model_validate(config)
    with pytest.raises(ValidationError, match="move frame_id into each camera"):
        GridSettings.model_validate(TWO | {"tf": {"mount": True}, "frame_id": "x"})
