"""The service in rmw_zenoh's ROS 2 graph: pinned hashes, attachment bytes and token strings, then a fake
Jazzy camera and a fake Humble camera (in a zenoh namespace) over real zenoh on loopback.

The expected strings are written out from rmw_zenoh's format (rmw_zenoh_cpp/src/detail/liveliness_utils.cpp):
  @ros2_lv/<domain>/<zid>/<nid>/<id>/<NN|MP|MS>/<enclave>/<namespace>/<node>[/<topic>/<type>/<hash>/<qos>]
"""

from __future__ import annotations

import re
import struct
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from gcdtrav.client.session.zenoh_args import zenoh_config
from zenoh_helpers import connecting_config, free_port, wait_until

pytest.importorskip("rosbags")
pytest.importorskip("xxhash")

from gcdtrav.service.bus.ros_graph import (
    CAMERA_SUBSCRIPTION_QOS,
    GRID_QOS,
    IMAGE_QOS,
    Entity,
    NodeName,
    Qos,
    TopicInfo,
    entity_gid,
    parse_publisher_token,
    rmw_attachment,
)
from gcdtrav.service.ros import cdr as ros

# Jazzy's RIHS01 type hashes (rosidl's type_description hash of each definition)
IMAGE_HASH = "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47"
COMPRESSED_IMAGE_HASH = "RIHS01_15640771531571185e2efc8a100baf923961a4d15d5569652e6cb6691e8e371a"
OCCUPANCY_GRID_HASH = "RIHS01_8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7"
ZID = "f1e2d3c4b5a6978812345678abcdef0"


def test_type_hashes_are_jazzys() -> None:
    assert ros.type_hash(ros.IMAGE) == IMAGE_HASH
    assert ros.type_hash(ros.COMPRESSED_IMAGE) == COMPRESSED_IMAGE_HASH
    assert ros.type_hash(ros.OCCUPANCY_GRID) == OCCUPANCY_GRID_HASH


def test_attachment_bytes() -> None:
    """int64 sequence, int64 timestamp (ns), then the gid as a zenoh-ext sequence: length 16 as a varint."""
    gid = bytes(range(16))
    expected = bytes.fromhex(
        "0100000000000000"  # sequence number 1
        "15cd853dfe9c9717"  # 1_700_000_000_123_456_789 ns
        "10"  # 16 bytes follow
        "000102030405060708090a0b0c0d0e0f"
    )
    attachment = rmw_attachment(1, 1_700_000_000_123_456_789, gid)
    assert attachment == expected and len(attachment) == 33
    assert attachment == struct.pack("<qqB", 1, 1_700_000_000_123_456_789, 16) + gid


def test_gid_is_xxh3_128_low_half_first() -> None:
    # XXH3-128 of no bytes is 0x99aa06d3014798d8_6001c324468d497f (xxHash's test vector); rmw_zenoh copies
    # low64 then high64, each in the machine's (little-endian) order
    assert entity_gid("") == bytes.fromhex("7f498d4624c30160d8984701d306aa99")
    token = f"@ros2_lv/0/{ZID}/0/0/NN/%/%/gcdtrav"
    assert Entity(ZID, 0, 0, "NN", NodeName(0, "/", "gcdtrav")).gid == entity_gid(token)


def test_qos_strings_write_only_what_differs_from_rmw_zenohs_defaults() -> None:
    assert Qos(depth=42).keyexpr() == "::,:,:,:,,"
    assert IMAGE_QOS.keyexpr() == "::,10:,:,:,,"
    assert GRID_QOS.keyexpr() == ":1:,1:,:,:,,"
    assert CAMERA_SUBSCRIPTION_QOS.keyexpr() == "2::,1:,:,:,,"
    assert Qos(reliable=False, depth=5).keyexpr() == "2::,5:,:,:,,"  # rclcpp's SensorDataQoS


def test_tokens_of_named_examples() -> None:
    node = NodeName(0, "/", "gcdtrav")
    assert Entity(ZID, 0, 0, "NN", node).token == f"@ros2_lv/0/{ZID}/0/0/NN/%/%/gcdtrav"
    camera = TopicInfo("/camera/front/image_raw", "sensor_msgs::msg::dds_::Image_", IMAGE_HASH, CAMERA_SUBSCRIPTION_QOS)
    assert Entity(ZID, 0, 1, "MS", node, camera).token == (
        f"@ros2_lv/0/{ZID}/0/1/MS/%/%/gcdtrav/%camera%front%image_raw/sensor_msgs::msg::dds_::Image_/"
        "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47/2::,1:,:,:,,"
    )
    robot = NodeName(3, "/robot1/perception", "gcdtrav")
    grid = TopicInfo("/cam/gcdtrav/grid/occupancy", "nav_msgs::msg::dds_::OccupancyGrid_", ros.HUMBLE_HASH, GRID_QOS)
    assert Entity(ZID, 4, 7, "MP", robot, grid).token == (
        f"@ros2_lv/3/{ZID}/4/7/MP/%/%robot1%perception/gcdtrav/%cam%gcdtrav%grid%occupancy/"
        "nav_msgs::msg::dds_::OccupancyGrid_/TypeHashNotSupported/:1:,1:,:,:,,"
    )


def test_tokens_of_rmw_zenohs_design_document() -> None:
    """The demo_nodes_cpp examples written out in rmw_zenoh's docs/design.md (graph cache section)."""
    string_hash = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
    chatter = "std_msgs::msg::dds_::String_"
    listener = NodeName(2, "/", "listener")
    zid = "aac3178e146ba6f1fc6e6a4085e77f21"
    assert Entity(zid, 0, 0, "NN", listener).token == "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    subscription = Entity(zid, 0, 10, "MS", listener, TopicInfo("/chatter", chatter, string_hash, Qos(depth=10)))
    assert subscription.token == (
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/"
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,10:,:,:,,"
    )
    talker = NodeName(2, "/", "talker")
    publisher = Entity(
        "8b20917502ee955ac4476e0266340d5c",
        0,
        10,
        "MP",
        talker,
        TopicInfo("/chatter", chatter, string_hash, Qos(depth=7)),
    )
    assert publisher.token == (
        "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,7:,:,:,,"
    )
    robot1 = ros.RosTopic("/robot1/chatter", "std_msgs/msg/String", "rmw_zenoh", 0)
    assert ros.topic_key(robot1) == f"0/robot1/chatter/{chatter}/{string_hash}"  # rosbags' hash of String


def test_publisher_tokens_are_parsed_others_ignored() -> None:
    token = (
        "@ros2_lv/0/abc123/5/6/MP/%/%robot/camera_driver/%camera%front%image_raw/"
        f"sensor_msgs::msg::dds_::Image_/{IMAGE_HASH}/2::,5:,:,:,,"
    )
    peer = parse_publisher_token(token)
    assert peer is not None
    assert (peer.domain, peer.zid, peer.topic, peer.dds_type, peer.type_hash) == (
        0,
        "abc123",
        "/camera/front/image_raw",
        "sensor_msgs::msg::dds_::Image_",
        IMAGE_HASH,
    )
    assert parse_publisher_token(token.replace("/MP/", "/MS/")) is None
    assert parse_publisher_token("@ros2_lv/0/abc123/5/5/NN/%/%/camera_driver") is None
    for malformed in (
        token.replace("/0/abc123", "/x/abc123"),  # domain
        token.replace("/MP/", "/XX/"),  # entity kind
        token.rsplit("/", 1)[0],  # no QoS
        "@ros2_lv/0/abc123/5",
    ):
        with pytest.raises(ros.RejectedInput, match="bad_graph_token"):
            parse_publisher_token(malformed)


def test_humble_and_namespaced_keys() -> None:
    humble = ros.parse_key(
        "robot1/0/camera/image_raw/sensor_msgs::msg::dds_::Image_/TypeHashNotSupported", "rmw_zenoh", "robot1"
    )
    assert (humble.topic, humble.namespace, humble.type_hash, humble.source) == (
        "/camera/image_raw",
        "robot1",
        "TypeHashNotSupported",
        "robot1/camera/image_raw",
    )
    t = humble.derived("/camera/image_raw/gcdtrav/traversability", ros.IMAGE)
    assert ros.topic_key(t) == (
        "robot1/0/camera/image_raw/gcdtrav/traversability/sensor_msgs::msg::dds_::Image_/TypeHashNotSupported"
    )
    jazzy = ros.parse_key(f"0/cam/sensor_msgs::msg::dds_::CompressedImage_/{COMPRESSED_IMAGE_HASH}", "rmw_zenoh")
    grid = jazzy.derived("/cam/gcdtrav/grid/occupancy", ros.OCCUPANCY_GRID)
    assert (
        ros.topic_key(grid) == f"0/cam/gcdtrav/grid/occupancy/nav_msgs::msg::dds_::OccupancyGrid_/{OCCUPANCY_GRID_HASH}"
    )
    with pytest.raises(ros.RejectedInput, match="zenoh namespace"):
        ros.parse_key("robot2/0/cam/sensor_msgs::msg::dds_::Image_/x", "rmw_zenoh", "robot1")


def test_output_topics_from_templates() -> None:
    templates = ["{topic}/gcdtrav/traversability", "/maps/occupancy"]
    assert ros.output_topic(templates[0], "/camera/front/image_raw") == "/camera/front/image_raw/gcdtrav/traversability"
    assert ros.output_topic(templates[1], "/camera/front/image_raw") == "/maps/occupancy"
    assert ros.is_output_topic("/camera/front/image_raw/gcdtrav/traversability", templates)
    assert ros.is_output_topic("/maps/occupancy", templates)
    assert not ros.is_output_topic("/camera/front/image_raw", templates)
    assert not ros.is_output_topic("/gcdtrav/traversability", templates)  # {topic} stands for at least one chunk


def test_depth_honours_is_bigendian() -> None:
    from gcdtrav.service.ros.cdr import decode_depth

    metres = np.array([[0.5, 1.25], [2.0, 7.75]], np.float32)
    millimetres = np.array([[500, 1250], [2000, 7750]], np.uint16)
    for encoding, values in (("32FC1", metres), ("16UC1", millimetres)):
        for big in (0, 1):
            raw = values.astype(values.dtype.newbyteorder(">" if big else "<")).view(np.uint8).ravel()
            message = ros.typestore().types[ros.IMAGE](
                header=ros.make_header(1.0, "depth"),
                height=2,
                width=2,
                encoding=encoding,
                is_bigendian=big,
                step=raw.size // 2,
                data=raw,
            )
            payload = bytes(ros.typestore().serialize_cdr(message, ros.IMAGE))
            np.testing.assert_allclose(decode_depth(payload), metres, rtol=1e-6)


# ---- over zenoh: a fake camera declares its publisher token ---------------------------------------------


class Camera:
    """A camera driver as rmw_zenoh would show it: node and publisher tokens, samples with the attachment,
    the test sends frames only once the service subscribed, as image_transport would."""

    def __init__(self, port: int, type_hash: str, zenoh_namespace: str) -> None:
        config = connecting_config(port)
        if zenoh_namespace:
            config.insert_json5("namespace", f'"{zenoh_namespace}"')
        self.session = zenoh.open(config)
        self.zid = str(self.session.info.zid())
        self.type_hash = type_hash
        self.key = f"0/camera/front/image_raw/sensor_msgs::msg::dds_::Image_/{type_hash}"
        self.tokens: dict[str, str] = {}  # every graph token seen: key -> "PUT" | "DELETE"
        self.samples: dict[str, tuple[bytes, bytes | None]] = {}
        self._lock = threading.Lock()
        self._declared: list[Any] = [
            self.session.liveliness().declare_subscriber("@ros2_lv/0/**", self._on_token, history=True),
            self.session.declare_subscriber("0/camera/front/image_raw/gcdtrav/**", self._on_sample),
        ]
        node = f"@ros2_lv/0/{self.zid}/0/0/NN/%/%/camera_driver"
        self.publisher_token = (
            f"@ros2_lv/0/{self.zid}/0/1/MP/%/%/camera_driver/%camera%front%image_raw/"
            f"sensor_msgs::msg::dds_::Image_/{type_hash}/2::,5:,:,:,,"
        )
        self.node_token = self.session.liveliness().declare_token(node)
        self.mp_token = self.session.liveliness().declare_token(self.publisher_token)

    def _on_token(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.tokens[str(sample.key_expr)] = "PUT" if sample.kind == zenoh.SampleKind.PUT else "DELETE"

    def _on_sample(self, sample: zenoh.Sample) -> None:
        attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
        with self._lock:
            self.samples[str(sample.key_expr)] = (sample.payload.to_bytes(), attachment)

    def live(self, prefix: str) -> list[str]:
        with self._lock:
            return sorted(k for k, v in self.tokens.items() if v == "PUT" and k.startswith(prefix))

    def send_frame(self) -> None:
        from ros_images import RGB, image_cdr

        gid = entity_gid(self.publisher_token)
        self.session.put(
            self.key, image_cdr(RGB, "rgb8", frame_id="front_optical"), attachment=rmw_attachment(1, 0, gid)
        )

    def close(self) -> None:
        for declared in self._declared:
            declared.undeclare()
        self.session.close()


def decoded_attachment(attachment: bytes) -> tuple[int, int, bytes]:
    sequence, stamp, length = struct.unpack_from("<qqB", attachment)
    assert length == 16 and len(attachment) == 33
    return sequence, stamp, attachment[17:]


@pytest.mark.parametrize(("distro", "zenoh_namespace"), [("jazzy", ""), ("humble", "robot1")])
def test_camera_is_subscribed_and_outputs_join_the_graph(
    tiny_backend: Any, tmp_path: Path, distro: str, zenoh_namespace: str
) -> None:
    from gcdtrav.schemas.settings import ServiceSettings

    from tools.loopback import in_process_service

    hashes = {"image": IMAGE_HASH, "compressed": COMPRESSED_IMAGE_HASH, "grid": OCCUPANCY_GRID_HASH}
    if distro == "humble":
        hashes = dict.fromkeys(hashes, ros.HUMBLE_HASH)
    prefix = f"{zenoh_namespace}/" if zenoh_namespace else ""
    source = f"{prefix}camera/front/image_raw"
    settings = ServiceSettings.model_validate(
        {
            "state_dir": str(tmp_path),
            "instance": f"graph-{distro}",
            "max_frame_age_s": None,  # frames stamped STAMP (2023)
            "inputs": [],
            "ros_inputs": [
                {"key": f"{prefix}0/**/sensor_msgs::msg::dds_::Image_/*", "zenoh_namespace": zenoh_namespace}
            ],
            "ros_output": {"enabled": True, "preview": "compressed"},
            "grids": [
                {
                    "source": source,
                    "intrinsics": {"fx": 30, "fy": 30, "cx": 16, "cy": 12, "width": 32, "height": 24},
                    "mount": {"z": 1.0, "pitch": 0.6},
                    "size_m": 6.0,
                    "resolution_m": 0.5,
                    "occupancy_grid": True,
                }
            ],
        }
    )
    with in_process_service(tiny_backend, settings) as (service, port):
        assert service.ros_graph is not None
        zid = service.ros_graph.zid
        node = f"@ros2_lv/0/{zid}/0/0/NN/%/%/gcdtrav"
        ours = f"@ros2_lv/0/{zid}/"
        camera = Camera(port, hashes["image"], zenoh_namespace)
        try:
            # the camera's publisher token is answered with a best-effort subscription token
            subscription = (
                f"@ros2_lv/0/{zid}/0/1/MS/%/%/gcdtrav/%camera%front%image_raw/"
                f"sensor_msgs::msg::dds_::Image_/{hashes['image']}/2::,1:,:,:,,"
            )
            assert wait_until(lambda: subscription in camera.live(ours), 60), camera.live(ours)
            assert camera.live(ours) == [node, subscription]

            # a malformed token in the graph is counted and changes nothing
            garbage = camera.session.liveliness().declare_token("@ros2_lv/0/not/a/token")
            assert wait_until(lambda: service.status().rejected_by_reason.get("bad_graph_token") == 1, 60)
            assert camera.live(ours) == [node, subscription]

            camera.send_frame()
            base = "0/camera/front/image_raw/gcdtrav"
            keys = {
                f"{base}/traversability/sensor_msgs::msg::dds_::Image_/{hashes['image']}": (2, "traversability"),
                f"{base}/uncertainty/sensor_msgs::msg::dds_::Image_/{hashes['image']}": (3, "uncertainty"),
                f"{base}/preview/compressed/sensor_msgs::msg::dds_::CompressedImage_/{hashes['compressed']}": (
                    4,
                    "preview%compressed",
                ),
                f"{base}/grid/occupancy/nav_msgs::msg::dds_::OccupancyGrid_/{hashes['grid']}": (5, "grid%occupancy"),
                f"{base}/grid/uncertainty/nav_msgs::msg::dds_::OccupancyGrid_/{hashes['grid']}": (
                    6,
                    "grid%uncertainty",
                ),
            }
            assert wait_until(lambda: set(keys) <= set(camera.samples), 30), sorted(camera.samples)
            assert wait_until(lambda: len(camera.live(ours)) == 2 + len(keys), 60), camera.live(ours)
            for key, (entity_id, suffix) in keys.items():
                dds_type, type_hash = key.split("/")[-2:]
                qos = ":1:,1:,:,:,," if "OccupancyGrid" in dds_type else "::,10:,:,:,,"
                token = (
                    f"@ros2_lv/0/{zid}/0/{entity_id}/MP/%/%/gcdtrav/%camera%front%image_raw%gcdtrav%{suffix}/"
                    f"{dds_type}/{type_hash}/{qos}"
                )
                assert token in camera.live(ours), (token, camera.live(ours))
                sequence, stamp, gid = decoded_attachment(camera.samples[key][1] or b"")
                assert sequence == 1 and abs(stamp - time.time_ns()) < 60e9 and gid == entity_gid(token)
            preview = ros.typestore().deserialize_cdr(
                camera.samples[next(k for k in keys if "preview" in k)][0], ros.COMPRESSED_IMAGE
            )
            assert preview.format == "rgb8; jpeg compressed bgr8"
            grid_key = next(k for k in keys if "grid/occupancy" in k)
            grid = ros.typestore().deserialize_cdr(camera.samples[grid_key][0], ros.OCCUPANCY_GRID)
            assert grid.info.width == 12 and (np.asarray(grid.data) >= 0).any()

            # a transient-local subscriber joining late gets the last grid from the publisher's cache
            from zenoh import ext

            late: list[bytes] = []
            history = ext.HistoryConfig(detect_late_publishers=True, max_samples=1)
            late_subscriber = ext.declare_advanced_subscriber(
                camera.session, grid_key, lambda s: late.append(s.payload.to_bytes()), history=history
            )
            assert wait_until(lambda: late, 60)
            assert late[0] == camera.samples[grid_key][0]
            late_subscriber.undeclare()
            garbage.undeclare()
            assert service.status().sources[source].processed == 1

            # the camera goes: its subscription token goes too; the service's node and publishers stay
            camera.mp_token.undeclare()
            assert wait_until(lambda: subscription not in camera.live(ours), 60)
            assert node in camera.live(ours) and len(camera.live(ours)) == 1 + len(keys)

            service.stop()  # every token of the service is undeclared
            assert wait_until(lambda: camera.live(ours) == [], 60), camera.live(ours)
        finally:
            camera.close()


def test_forgotten_outputs_take_their_publisher_tokens_along(tmp_path: Path) -> None:
    """A source the service stops tracking (issue 12's bounds) leaves no publisher token behind."""
    from gcdtrav.schemas.settings import ServiceSettings
    from gcdtrav.service.bus.ros_graph import RosGraph

    settings = ServiceSettings.model_validate({"state_dir": str(tmp_path), "ros_inputs": [{"key": "0/**"}]})
    session = zenoh.open(connecting_config(1))  # no peer needed: its own tokens are visible to the session
    try:
        rejected: list[str] = []
        graph = RosGraph(session, settings, lambda _name, reason, _detail: rejected.append(reason))
        camera = ros.parse_key(f"0/cam/sensor_msgs::msg::dds_::Image_/{IMAGE_HASH}", "rmw_zenoh")
        publisher = graph.publisher(
            camera.derived("/cam/gcdtrav/traversability", ros.IMAGE), IMAGE_QOS, zenoh.Encoding.APPLICATION_CDR
        )
        publisher.put(b"\x00\x01\x00\x00")

        def live_publishers() -> list[str]:
            replies = session.liveliness().get("@ros2_lv/0/**", timeout=2.0)
            return [str(r.ok.key_expr) for r in replies if r.ok is not None and "/MP/" in str(r.ok.key_expr)]

        assert live_publishers() == [publisher.entity.token]
        graph.forget({publisher.key})
        assert wait_until(lambda: live_publishers() == [], 60)
        graph.close()
        assert rejected == []
    finally:
        session.close()


# ---- /tf and /tf_static: subscription tokens with tf2_ros's listener QoS ---------------------------------

TF_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"
TF_TYPE = "tf2_msgs::msg::dds_::TFMessage_"


def tf_settings(tmp_path: Path, **tf: str) -> Any:
    from gcdtrav.schemas.settings import ServiceSettings

    camera = {"source": "cam", "intrinsics": {"fx": 30, "fy": 30, "cx": 16, "cy": 12, "width": 32, "height": 24}}
    grid = camera | {"tf": {"mount": True, "pose": True} | tf}
    return ServiceSettings.model_validate({"state_dir": str(tmp_path), "grids": [grid]})


def test_tf_qos_strings_are_tf2_ros_listeners() -> None:
    from gcdtrav.service.bus.ros_graph import TF_QOS, TF_STATIC_QOS

    assert TF_STATIC_QOS.keyexpr() == ":1:,100:,:,:,,"  # StaticListenerQoS: reliable, transient local, keep-last 100
    assert TF_QOS.keyexpr() == "::,100:,:,:,,"  # DynamicListenerQoS: reliable, volatile, keep-last 100


def test_tf_keys_join_the_graph_only_in_rmw_zenohs_layout(tmp_path: Path) -> None:
    from gcdtrav.service.bus.ros_graph import TF_QOS, TF_STATIC_QOS, GraphInput, graph_inputs, tf_graph_input

    assert graph_inputs(tf_settings(tmp_path)) == [
        GraphInput(f"*/tf_static/{TF_TYPE}/*", "", TF_STATIC_QOS),
        GraphInput(f"*/tf/{TF_TYPE}/*", "", TF_QOS),
    ]
    assert graph_inputs(tf_settings(tmp_path, tf_key="tf", tf_static_key="tf_static")) == []  # the bridge's keys
    assert tf_graph_input(f"robot1/*/tf/{TF_TYPE}/*", TF_QOS) == GraphInput(
        f"robot1/*/tf/{TF_TYPE}/*", "robot1", TF_QOS
    )
    assert tf_graph_input(f"0/robot1/tf/{TF_TYPE}/*", TF_QOS) == GraphInput(f"0/robot1/tf/{TF_TYPE}/*", "", TF_QOS)
    assert tf_graph_input(f"robot1/tf/{TF_TYPE}/*", TF_QOS) is None  # no domain chunk: not rmw_zenoh's layout
    assert tf_graph_input("tf/bad", TF_QOS) is None


def test_tf_publishers_are_answered_with_listener_subscription_tokens(tmp_path: Path) -> None:
    """A robot's /tf_static and /tf publisher tokens (as robot_state_publisher's rmw_zenoh declares them): the
    service declares a subscription for each with tf2_ros's listener QoS, and withdraws it with the publisher."""
    from gcdtrav.service.bus.ros_graph import RosGraph

    port = free_port()
    robot = zenoh.open(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False))
    service = zenoh.open(connecting_config(port))
    graph = None
    try:
        robot_zid = str(robot.info.zid())
        node = robot.liveliness().declare_token(f"@ros2_lv/0/{robot_zid}/0/0/NN/%/%/robot_state_publisher")
        publishers = {
            topic: robot.liveliness().declare_token(
                f"@ros2_lv/0/{robot_zid}/0/{n}/MP/%/%/robot_state_publisher/%{topic}/{TF_TYPE}/{TF_HASH}/{qos}"
            )
            for n, (topic, qos) in enumerate((("tf_static", ":1:,1:,:,:,,"), ("tf", "::,100:,:,:,,")), start=1)
        }
        seen: dict[str, str] = {}
        watcher = robot.liveliness().declare_subscriber(
            "@ros2_lv/0/**", lambda s: seen.__setitem__(str(s.key_expr), str(s.kind)), history=True
        )
        rejected: list[str] = []
        graph = RosGraph(service, tf_settings(tmp_path), lambda _name, reason, _detail: rejected.append(reason))
        graph.start()
        ours = f"@ros2_lv/0/{graph.zid}/"

        def live() -> list[str]:
            return sorted(k for k, v in seen.items() if k.startswith(ours) and v == str(zenoh.SampleKind.PUT))

        def without_ids() -> list[str]:  # ids follow discovery order, which zenoh does not fix
            return sorted(re.sub(r"^(@ros2_lv/0/\w+/0/)\d+/", r"\1<id>/", token) for token in live())

        subscriptions = [
            f"{ours}0/<id>/MS/%/%/gcdtrav/%{topic}/{TF_TYPE}/{TF_HASH}/{qos}"
            for topic, qos in (("tf_static", ":1:,100:,:,:,,"), ("tf", "::,100:,:,:,,"))
        ]
        node_token = f"{ours}0/<id>/NN/%/%/gcdtrav"  # with the first subscription (the default keys' domain is '*')
        assert wait_until(lambda: without_ids() == sorted([node_token, *subscriptions]), 60), live()
        assert f"{ours}0/0/NN/%/%/gcdtrav" in live()

        publishers["tf"].undeclare()  # the /tf publisher goes: its subscription token goes too
        assert wait_until(lambda: without_ids() == sorted([node_token, subscriptions[0]]), 60), live()
        graph.close()
        graph = None
        assert wait_until(lambda: live() == [], 60), live()
        assert rejected == []
        watcher.undeclare()
        publishers["tf_static"].undeclare()
        node.undeclare()
    finally:
        if graph is not None:
            graph.close()
        service.close()
        robot.close()
