"""The one ROS image reader (schemas/ros_image.py, numpy only) reads what rosbags reads, as rosbags-image
decodes it: every encoding, padded rows, both byte orders, compressed images; and unusable payloads say why,
with the reason the service counts."""

from __future__ import annotations

import numpy as np
import pytest
from gcdtrav.schemas import ros_image as ri
from gcdtrav.schemas.images import encode_jpeg
from gcdtrav.schemas.inputs import RejectedInput

from tools.ros_fixtures import compressed_image_cdr, image_cdr

cdr = pytest.importorskip("gcdtrav.service.ros.cdr")
image_module = pytest.importorskip("rosbags.image")

CHANNELS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "mono16": 2, "bayer_rggb8": 1, "bayer_grbg8": 1}


def rosbags_rgb(payload: bytes) -> np.ndarray:
    """rosbags' reading of an Image, converted as the service converted it before the one reader."""
    message = cdr.typestore().deserialize_cdr(payload, ri.IMAGE)
    if str(message.encoding) == "mono16":
        gray = (np.asarray(image_module.message_to_cvimage(message), np.uint16) >> 8).astype(np.uint8)
        return np.repeat(gray[:, :, None], 3, axis=2)
    return np.asarray(image_module.message_to_cvimage(message, "rgb8"), np.uint8)


@pytest.mark.parametrize("encoding", sorted(CHANNELS))
def test_raw_images_decode_as_the_service_decodes_them(encoding: str) -> None:
    pixels = np.random.default_rng(3).integers(0, 256, (30, 41, CHANNELS[encoding]), dtype=np.uint8)
    payload = image_cdr(pixels, 12.25, "cam", encoding)
    mine = ri.decode_ros_image(payload, ri.IMAGE, 10**7)
    np.testing.assert_array_equal(mine.image, rosbags_rgb(payload))
    assert (mine.stamp, mine.frame_id) == (12.25, "cam")
    service = cdr.decode_ros_image(payload, ri.IMAGE, 10**7)  # the service's: the same reading, and its header
    np.testing.assert_array_equal(service.image, mine.image)
    assert (service.header.stamp.sec, service.header.stamp.nanosec, service.header.frame_id) == (12, 250_000_000, "cam")


def test_a_big_endian_mono16_image_reads_its_top_byte() -> None:
    values = np.random.default_rng(5).integers(0, 65536, (6, 7), dtype=np.uint16)
    image = cdr.typestore().types[ri.IMAGE](
        header=cdr.make_header(3.0, "x"), height=6, width=7, encoding="mono16", is_bigendian=1, step=14,
        data=np.frombuffer(values.astype(">u2").tobytes(), np.uint8),
    )  # fmt: skip
    payload = bytes(cdr.typestore().serialize_cdr(image, ri.IMAGE))
    decoded = ri.decode_ros_image(payload, ri.IMAGE, 10**7).image
    np.testing.assert_array_equal(decoded[:, :, 0], (values >> 8).astype(np.uint8))
    np.testing.assert_array_equal(decoded, rosbags_rgb(payload))


def test_the_stamp_keeps_its_nanoseconds() -> None:
    header = cdr.header_of(1_732_000_000, 123_456_789, "cam")
    image = cdr.typestore().types[ri.IMAGE](
        header=header, height=1, width=1, encoding="mono8", is_bigendian=0, step=1, data=np.zeros(1, np.uint8)
    )
    frame = cdr.decode_ros_image(bytes(cdr.typestore().serialize_cdr(image, ri.IMAGE)), ri.IMAGE, 10)
    assert (frame.header.stamp.sec, frame.header.stamp.nanosec) == (1_732_000_000, 123_456_789)


def test_padded_rows_and_compressed_images_from_rosbags() -> None:
    pixels = np.random.default_rng(4).integers(0, 256, (30, 41, 3), dtype=np.uint8)
    padded = np.zeros((30, 128), np.uint8)
    padded[:, :123] = pixels[:, :, ::-1].reshape(30, -1)
    image = cdr.typestore().types[ri.IMAGE](
        header=cdr.make_header(99.5, "x"), height=30, width=41, encoding="bgr8", is_bigendian=0, step=128,
        data=padded.ravel(),
    )  # fmt: skip
    decoded = ri.decode_ros_image(bytes(cdr.typestore().serialize_cdr(image, ri.IMAGE)), ri.IMAGE, 10**7)
    np.testing.assert_array_equal(decoded.image, pixels)
    assert decoded.stamp == 99.5
    jpeg = cdr.compressed_jpeg_cdr(cdr.make_header(5.5, "y"), encode_jpeg(pixels))
    decoded = ri.decode_ros_image(jpeg, ri.COMPRESSED_IMAGE, 10**7)
    assert decoded.image.shape == (30, 41, 3) and (decoded.stamp, decoded.frame_id) == (5.5, "y")
    ours = cdr.decode_ros_image(compressed_image_cdr(encode_jpeg(pixels), 7.0, "z"), ri.COMPRESSED_IMAGE, 10**7)
    assert (ours.stamp, ours.frame_id) == (7.0, "z") and ri.peek_stamp(jpeg) == 5.5


GOOD = image_cdr(np.zeros((4, 4, 3), np.uint8), 1.0, "cam")


@pytest.mark.parametrize(
    ("payload", "msgtype", "reason", "message"),
    [
        (b"", ri.IMAGE, "bad_cdr", "encapsulation"),
        (b"\x00\x01\x00\x00\x01", ri.IMAGE, "bad_cdr", "truncated"),
        (GOOD[:-5], ri.IMAGE, "bad_cdr", "sequence"),
        (GOOD + b"\x00" * 4, ri.IMAGE, "bad_cdr", "4 bytes after the message"),
        (GOOD.replace(b"cam\x00", b"ca\xff\x00"), ri.IMAGE, "bad_cdr", "not UTF-8"),
        (GOOD.replace(b"cam\x00", b"cams"), ri.IMAGE, "bad_cdr", "terminator"),
        (image_cdr(np.zeros((4, 4, 1), np.uint8), 1.0, encoding="yuv422"), ri.IMAGE, "unknown_encoding", "yuv422"),
        (image_cdr(np.zeros((40, 40, 3), np.uint8), 1.0), ri.IMAGE, "too_many_pixels", "limit of 100 pixels"),
        (image_cdr(np.zeros((4, 4, 3), np.uint8), 1.0, "a" * 300), ri.IMAGE, "frame_id_too_long", "300"),
        (compressed_image_cdr(b"not a jpeg", 1.0), ri.COMPRESSED_IMAGE, "undecodable", "CompressedImage"),
        (compressed_image_cdr(b"", 1.0), "sensor_msgs/msg/PointCloud2", "unsupported_ros_type", "PointCloud2"),
    ],
)
def test_unusable_payloads_say_why(payload: bytes, msgtype: str, reason: str, message: str) -> None:
    with pytest.raises(RejectedInput, match=message) as err:
        ri.decode_ros_image(payload, msgtype, 100 if "limit" in message else 10**7)
    assert err.value.reason == reason


def test_up_to_three_padding_bytes_are_read_as_rosbags_reads_them() -> None:
    padded = GOOD + b"\x00" * 3
    cdr.typestore().deserialize_cdr(padded, ri.IMAGE)  # rosbags reads it too
    assert ri.decode_ros_image(padded, ri.IMAGE, 10**7).frame_id == "cam"
