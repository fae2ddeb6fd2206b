"""The relay's own ROS image codec agrees with the service's (rosbags) on every encoding it reads."""

from __future__ import annotations

import numpy as np
import pytest
from gcdtrav.client.relay import ros_camera as rc
from gcdtrav.schemas.images import encode_jpeg

cdr = pytest.importorskip("gcdtrav.service.ros.cdr")
pytest.importorskip("rosbags")

CHANNELS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "mono16": 2, "bayer_rggb8": 1, "bayer_grbg8": 1}


@pytest.mark.parametrize("encoding", sorted(CHANNELS))
def test_raw_images_decode_as_the_service_decodes_them(encoding: str) -> None:
    pixels = np.random.default_rng(3).integers(0, 256, (30, 41, CHANNELS[encoding]), dtype=np.uint8)
    payload = rc.image_cdr(pixels, 12.25, "cam", encoding)
    mine, stamp, frame_id = rc.decode_ros_image(payload, rc.IMAGE, 10**7)
    reference = cdr.decode_ros_image(payload, rc.IMAGE, 10**7)
    np.testing.assert_array_equal(mine, reference.image)
    assert (stamp, frame_id) == (reference.stamp, reference.frame_id) == (12.25, "cam")


def test_padded_rows_and_compressed_images_from_rosbags() -> None:
    pixels = np.random.default_rng(4).integers(0, 256, (30, 41, 3), dtype=np.uint8)
    padded = np.zeros((30, 128), np.uint8)
    padded[:, :123] = pixels[:, :, ::-1].reshape(30, -1)
    image = cdr.typestore().types[rc.IMAGE](
        header=cdr.make_header(99.5, "x"), height=30, width=41, encoding="bgr8", is_bigendian=0, step=128,
        data=padded.ravel(),
    )  # fmt: skip
    decoded, stamp, _ = rc.decode_ros_image(bytes(cdr.typestore().serialize_cdr(image, rc.IMAGE)), rc.IMAGE, 10**7)
    np.testing.assert_array_equal(decoded, pixels)
    assert stamp == 99.5
    jpeg = cdr.compressed_jpeg_cdr(cdr.make_header(5.5, "y"), encode_jpeg(pixels))
    decoded, stamp, frame_id = rc.decode_ros_image(jpeg, rc.COMPRESSED_IMAGE, 10**7)
    assert decoded.shape == (30, 41, 3) and (stamp, frame_id) == (5.5, "y")
    ours = cdr.decode_ros_image(rc.compressed_image_cdr(encode_jpeg(pixels), 7.0, "z"), rc.COMPRESSED_IMAGE, 10**7)
    assert (ours.stamp, ours.frame_id) == (7.0, "z") and rc.peek_stamp(jpeg) == 5.5


@pytest.mark.parametrize(
    ("payload", "msgtype", "message"),
    [
        (b"", rc.IMAGE, "not CDR"),
        (b"\x00\x01\x00\x00\x01", rc.IMAGE, "truncated"),
        (rc.image_cdr(np.zeros((4, 4, 3), np.uint8), 1.0)[:-5], rc.IMAGE, "truncated"),
        (rc.image_cdr(np.zeros((4, 4, 1), np.uint8), 1.0, encoding="yuv422"), rc.IMAGE, "encoding 'yuv422'"),
        (rc.image_cdr(np.zeros((40, 40, 3), np.uint8), 1.0), rc.IMAGE, "limit 100"),
        (rc.compressed_image_cdr(b"not a jpeg", 1.0), rc.COMPRESSED_IMAGE, "CompressedImage"),
        (rc.compressed_image_cdr(b"", 1.0), "sensor_msgs/msg/PointCloud2", "not an image type"),
    ],
)
def test_unusable_payloads_say_why(payload: bytes, msgtype: str, message: str) -> None:
    with pytest.raises(rc.RosImageError, match=message):
        rc.decode_ros_image(payload, msgtype, 100 if "limit" in message else 10**7)


def test_camera_keys_of_both_layouts() -> None:
    assert rc.ros_camera_key("/camera/front/image_raw", "rmw_zenoh") == "0/camera/front/image_raw/*/*"
    assert rc.ros_camera_key("/cam", "rmw_zenoh", 7, "robot1") == "robot1/7/cam/*/*"
    assert rc.ros_camera_key("/camera/front/image_raw", "bridge") == "camera/front/image_raw"
    key = "0/camera/front/image_raw/sensor_msgs::msg::dds_::CompressedImage_/RIHS01_abc"
    assert rc.ros_type_of_key(key) == rc.COMPRESSED_IMAGE
    assert rc.ros_type_of_key("camera/front") is None
