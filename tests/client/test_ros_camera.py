"""The relay's camera keys: rmw_zenoh's and the bridge's layouts, and the message type a key names."""

from __future__ import annotations

from gcdtrav.client.relay.ros_camera import ros_camera_key, ros_type_of_key
from gcdtrav.schemas.ros_image import COMPRESSED_IMAGE


def test_camera_keys_of_both_layouts() -> None:
    assert ros_camera_key("/camera/front/image_raw", "rmw_zenoh") == "0/camera/front/image_raw/*/*"
    assert ros_camera_key("/cam", "rmw_zenoh", 7, "robot1") == "robot1/7/cam/*/*"
    assert ros_camera_key("/camera/front/image_raw", "bridge") == "camera/front/image_raw"
    key = "0/camera/front/image_raw/sensor_msgs::msg::dds_::CompressedImage_/RIHS01_abc"
    assert ros_type_of_key(key) == COMPRESSED_IMAGE
    assert ros_type_of_key("camera/front") is None
