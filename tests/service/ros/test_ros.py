"""ROS 2 images over Zenoh: CDR in (rmw_zenoh and bridge layouts), maps out as msgpack and as ROS Images."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import zenoh
from zenoh_helpers import connecting_config, subscribed_elsewhere, wait_until

pytest.importorskip("rosbags")

from gcdtrav.service.ros import cdr as ros
from ros_images import RGB, STAMP, image_cdr

BAYER_TO_OPENCV = {  # as cv_bridge: ROS names the top-left 2x2 pattern, OpenCV the second row's
    "bayer_rggb8": cv2.COLOR_BayerBG2RGB,
    "bayer_bggr8": cv2.COLOR_BayerRG2RGB,
    "bayer_gbrg8": cv2.COLOR_BayerGR2RGB,
    "bayer_grbg8": cv2.COLOR_BayerGB2RGB,
}
BAYER_OFFSETS = {"bayer_rggb8": "RGGB", "bayer_bggr8": "BGGR", "bayer_gbrg8": "GBRG", "bayer_grbg8": "GRBG"}


def compressed_cdr(data: bytes, fmt: str, stamp: float = STAMP, frame_id: str = "cam") -> bytes:
    message = ros.typestore().types[ros.COMPRESSED_IMAGE](
        header=ros.make_header(stamp, frame_id), format=fmt, data=np.frombuffer(data, np.uint8)
    )
    return bytes(ros.typestore().serialize_cdr(message, ros.COMPRESSED_IMAGE))


def bayer_mosaic(rgb: np.ndarray, pattern: str) -> np.ndarray:
    channel = {"R": 0, "G": 1, "B": 2}
    mosaic = np.empty(rgb.shape[:2], np.uint8)
    for k, (dy, dx) in enumerate([(0, 0), (0, 1), (1, 0), (1, 1)]):
        mosaic[dy::2, dx::2] = rgb[dy::2, dx::2, channel[pattern[k]]]
    return mosaic


GRAY16 = (np.arange(24 * 32, dtype=np.uint16).reshape(24, 32) * 85).astype(np.uint16)
CASES: dict[str, tuple[np.ndarray, np.ndarray]] = {
    "rgb8": (RGB, RGB),
    "bgr8": (RGB[:, :, ::-1], RGB),
    "rgba8": (np.dstack([RGB, np.full(RGB.shape[:2], 255, np.uint8)]), RGB),
    "bgra8": (np.dstack([RGB[:, :, ::-1], np.full(RGB.shape[:2], 9, np.uint8)]), RGB),
    "mono8": (RGB[:, :, 1], np.repeat(RGB[:, :, 1:2], 3, axis=2)),
    "mono16": (GRAY16, np.repeat((GRAY16 >> 8).astype(np.uint8)[:, :, None], 3, axis=2)),
    **{
        name: (bayer_mosaic(RGB, BAYER_OFFSETS[name]), cv2.cvtColor(bayer_mosaic(RGB, BAYER_OFFSETS[name]), code))
        for name, code in BAYER_TO_OPENCV.items()
    },
}


@pytest.mark.parametrize("encoding", sorted(CASES))
def test_every_raw_encoding_decodes_pixel_for_pixel(encoding: str) -> None:
    raw, expected = CASES[encoding]
    frame = ros.decode_ros_image(image_cdr(raw, encoding, frame_id="front"), ros.IMAGE, 10**7)
    np.testing.assert_array_equal(frame.image, expected)
    assert frame.stamp == pytest.approx(STAMP, abs=1e-9) and frame.frame_id == "front"


def test_row_padding_is_removed() -> None:
    frame = ros.decode_ros_image(image_cdr(RGB, "rgb8", step=32 * 3 + 8), ros.IMAGE, 10**7)
    np.testing.assert_array_equal(frame.image, RGB)


@pytest.mark.parametrize("fmt", ["jpeg", "png"])
def test_compressed_images(fmt: str) -> None:
    _, encoded = cv2.imencode(".jpg" if fmt == "jpeg" else ".png", RGB[:, :, ::-1])
    frame = ros.decode_ros_image(compressed_cdr(encoded.tobytes(), fmt), ros.COMPRESSED_IMAGE, 10**7)
    expected = cv2.imdecode(encoded, cv2.IMREAD_COLOR)[:, :, ::-1]
    np.testing.assert_array_equal(frame.image, expected)


@pytest.mark.parametrize(
    ("payload", "msgtype", "reason"),
    [
        (image_cdr(RGB, "rgb8")[:60], ros.IMAGE, "bad_cdr"),
        (b"\x00\x01\x00\x00garbage", ros.IMAGE, "bad_cdr"),
        (image_cdr(RGB, "yuv422"), ros.IMAGE, "unknown_encoding"),
        (image_cdr(RGB, "rgb8", width=40), ros.IMAGE, "size_mismatch"),
        (image_cdr(RGB, "rgb8", data=np.zeros(10, np.uint8)), ros.IMAGE, "size_mismatch"),
        (image_cdr(RGB, "rgb8", step=10), ros.IMAGE, "size_mismatch"),
        (image_cdr(RGB, "rgb8", width=100000, height=100000, data=np.zeros(3, np.uint8)), ros.IMAGE, "too_many_pixels"),
        (compressed_cdr(b"not a jpeg", "jpeg"), ros.COMPRESSED_IMAGE, "undecodable"),
        (image_cdr(RGB, "rgb8"), "sensor_msgs/msg/PointCloud2", "unsupported_ros_type"),
    ],
)
def test_bad_ros_payloads(payload: bytes, msgtype: str, reason: str) -> None:
    with pytest.raises(ros.RejectedInput) as info:
        ros.decode_ros_image(payload, msgtype, 10**7)
    assert info.value.reason == reason


def test_keys_of_both_layouts() -> None:
    image_hash = ros.type_hash(ros.IMAGE)
    assert image_hash.startswith("RIHS01_") and len(image_hash) == 7 + 64
    key = f"0/robot/front/image_raw/sensor_msgs::msg::dds_::Image_/{image_hash}"
    topic = ros.parse_key(key, "rmw_zenoh")
    assert (topic.topic, topic.msgtype, topic.source, topic.domain, topic.type_hash) == (
        "/robot/front/image_raw",
        ros.IMAGE,
        "robot/front/image_raw",
        0,
        image_hash,
    )
    assert ros.topic_key(topic.derived("/robot/front/image_raw/gcdtrav/traversability", ros.IMAGE)) == (
        f"0/robot/front/image_raw/gcdtrav/traversability/sensor_msgs::msg::dds_::Image_/{image_hash}"
    )
    bridge = ros.parse_key("cam/left", "bridge")
    assert bridge.topic == "/cam/left" and bridge.msgtype is None
    preview = bridge.derived("/cam/left/gcdtrav/preview/compressed", ros.COMPRESSED_IMAGE)
    assert ros.topic_key(preview) == "cam/left/gcdtrav/preview/compressed"
    with pytest.raises(ros.RejectedInput, match="bad_ros_key"):
        ros.parse_key("0/robot/front", "rmw_zenoh")


# ---- through a real zenoh session ----------------------------------------------------------------------


def decode_float_image(payload: bytes) -> tuple[np.ndarray, Any]:
    message = ros.typestore().deserialize_cdr(payload, ros.IMAGE)
    assert message.encoding == "32FC1"
    values = np.frombuffer(bytes(message.data), dtype="<f4").reshape(message.height, message.width)
    return values, message.header


def test_ros_in_maps_out_both_layouts(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    from gcdtrav.client import Maps, TraversabilityClient
    from gcdtrav.schemas.settings import ServiceSettings

    from tools.loopback import in_process_service

    settings = ServiceSettings.model_validate(
        {
            "state_dir": str(tmp_path),
            "instance": "ros-test",
            "max_frame_age_s": None,  # frames stamped STAMP (2023)
            "full_resolution": True,
            "inputs": [],
            "ros_inputs": [
                {"key": "0/**/sensor_msgs::msg::dds_::Image_/*", "layout": "rmw_zenoh"},
                {"key": "cam/left", "layout": "bridge", "message_type": ros.COMPRESSED_IMAGE},
            ],
            "ros_output": {"enabled": True, "preview": "compressed"},
        }
    )
    with in_process_service(tiny_backend, settings) as (service, port):
        client = TraversabilityClient(config=connecting_config(port), timeout=5.0)
        maps: dict[str, Maps] = {}
        ros_out: dict[str, tuple[bytes, bytes | None]] = {}
        subscriptions = [
            client.subscribe_maps("**", lambda m: maps.__setitem__(m.header.source, m)),
            client.session.declare_subscriber(
                "**/gcdtrav/**",
                lambda s: ros_out.__setitem__(
                    str(s.key_expr), (s.payload.to_bytes(), s.attachment.to_bytes() if s.attachment else None)
                ),
            ),
        ]
        try:
            image_hash = ros.type_hash(ros.IMAGE)
            rmw_key = f"0/robot/front/image_raw/sensor_msgs::msg::dds_::Image_/{image_hash}"
            for key in (rmw_key, "cam/left"):  # the service's input subscriptions reached the robot's session
                assert subscribed_elsewhere(client.session, key), key
            for key in (service.keys.maps("probe"), "robot/front/image_raw/gcdtrav/traversability/x"):
                assert subscribed_elsewhere(service.session, key), key  # the robot's subscriptions, the service's
            client.session.put(
                rmw_key, image_cdr(RGB, "rgb8", frame_id="front_optical"), encoding=zenoh.Encoding.APPLICATION_CDR
            )
            _, jpeg = cv2.imencode(".jpg", RGB[:, :, ::-1])
            client.session.put("cam/left", compressed_cdr(jpeg.tobytes(), "jpeg", stamp=STAMP + 1, frame_id="left"))
            assert wait_until(lambda: {"robot/front/image_raw", "cam/left"} <= set(maps), 60)
            client.session.put(rmw_key, image_cdr(RGB, "rgb8")[:50])  # truncated: counted, nothing else happens
            front = maps["robot/front/image_raw"]
            assert front.header.stamp == pytest.approx(STAMP, abs=1e-6) and front.header.frame_id == "front_optical"
            assert front.header.key == rmw_key and front.header.image_size == (32, 24)
            left = maps["cam/left"]
            assert left.header.stamp == pytest.approx(STAMP + 1, abs=1e-6) and left.header.frame_id == "left"

            t_key = f"0/robot/front/image_raw/gcdtrav/traversability/sensor_msgs::msg::dds_::Image_/{image_hash}"
            assert wait_until(lambda: t_key in ros_out, 60), sorted(ros_out)
            values, header = decode_float_image(ros_out[t_key][0])
            assert header.frame_id == "front_optical" and header.stamp.sec == int(STAMP)
            assert header.stamp.nanosec == 250_000_000
            assert front.traversability_full is not None
            np.testing.assert_allclose(values, front.traversability_full, atol=0.51 / 65535)
            assert ros_out[t_key][1] is not None  # rmw_zenoh subscribers expect the attachment
            u_key = t_key.replace("/traversability/", "/uncertainty/")
            assert wait_until(lambda: u_key in ros_out, 60)
            np.testing.assert_allclose(
                decode_float_image(ros_out[u_key][0])[0], front.uncertainty_full, atol=0.51 / 65535
            )
            preview_key = "cam/left/gcdtrav/preview/compressed"  # image_transport's compressed subtopic
            assert wait_until(lambda: preview_key in ros_out, 60)
            preview = ros.typestore().deserialize_cdr(ros_out[preview_key][0], ros.COMPRESSED_IMAGE)
            assert preview.format == "rgb8; jpeg compressed bgr8"
            assert cv2.imdecode(np.asarray(preview.data), cv2.IMREAD_COLOR) is not None
            assert "cam/left/gcdtrav/traversability" in ros_out

            by_stamp = client.patch("robot/front/image_raw", 3, 3, stamp=STAMP)
            assert by_stamp.seq == 0 and by_stamp.frame_id == "front_optical"
            assert wait_until(lambda: service.status().rejected_by_reason.get("bad_cdr") == 1, 60)
            ros_keys = [key for key in ros_out if not key.startswith("gcdtrav/")]
            assert len(ros_keys) == 6  # 3 per input; nothing fed back although outputs match the wide rmw input
            # The maps go out just before their frame is counted (on the output thread, with a spare CPU).
            assert wait_until(lambda: service.status().sources["robot/front/image_raw"].processed == 1, 60)
        finally:
            for subscription in subscriptions:
                subscription.undeclare()
            client.close()


def test_topic_key_round_trips_through_parse_key() -> None:
    topic = ros.RosTopic(
        "/camera/front/image_raw", ros.COMPRESSED_IMAGE, "rmw_zenoh", 3, "robot1", ros.type_hash(ros.COMPRESSED_IMAGE)
    )
    assert ros.parse_key(ros.topic_key(topic), "rmw_zenoh", "robot1") == topic
    bridge = ros.RosTopic("/camera/front/image_raw", None, "bridge")
    assert ros.parse_key(ros.topic_key(bridge), "bridge") == bridge
