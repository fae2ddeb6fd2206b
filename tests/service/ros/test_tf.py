"""tf without ROS: TFMessage CDR against its definition, tf2's input checks, the tree's lookups at its edges."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest

pytest.importorskip("rosbags")

from gcdtrav.schemas.inputs import RejectedInput
from gcdtrav.service.grid.geometry import CameraMount, mount_from_axes
from gcdtrav.service.ros import cdr as ros
from gcdtrav.service.ros.tf import (
    TF_MESSAGE,
    StampedTransform,
    Transform,
    decode_tf_message,
    interpolate,
)
from gcdtrav.service.ros.tf_tree import MAX_FRAMES, TfLookupError, TransformTree

from tools.ros_fixtures import tf_message_cdr

# Jazzy's type hash of tf2_msgs/msg/TFMessage, as rmw_zenoh puts it in keys and liveliness tokens (the same hash
# appears in third-party rmw_zenoh peers' tokens; rosbags computes it from the message definitions)
TF_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"


def yaw_q(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def st(parent: str, child: str, stamp: float, xyz=(0.0, 0.0, 0.0), q=(0.0, 0.0, 0.0, 1.0)) -> StampedTransform:  # type: ignore[no-untyped-def]
    return StampedTransform(parent, child, stamp, Transform(tuple(xyz), tuple(q)))  # type: ignore[arg-type]


def test_a_tfmessage_has_the_byte_layout_of_its_definition() -> None:
    """tf2_msgs/TFMessage = TransformStamped[]; little-endian CDR, alignment counted after the 4-byte
    encapsulation header: a sequence length, Header (Time sec int32, nanosec uint32, frame_id string),
    child_frame_id string, Transform (Vector3 and Quaternion: float64 each, aligned to 8)."""
    q = yaw_q(0.5)
    built = tf_message_cdr([st("odom", "base_link", 12.5, (1.0, 2.0, 0.0), q)])
    by_hand = b"\x00\x01\x00\x00"  # CDR_LE encapsulation, options 0
    by_hand += struct.pack("<I", 1)  # 1 transform                      offset 0
    by_hand += struct.pack("<iI", 12, 500_000_000)  # header.stamp       offset 4
    by_hand += struct.pack("<I", 5) + b"odom\x00" + b"\x00" * 3  # frame_id: length with its NUL, pad to 24
    by_hand += struct.pack("<I", 10) + b"base_link\x00" + b"\x00" * 2  # child_frame_id, pad to 40 (float64)
    by_hand += struct.pack("<3d", 1.0, 2.0, 0.0) + struct.pack("<4d", *q)  # offsets 40 and 64
    assert len(by_hand) == 4 + 96
    assert built == by_hand
    kept, refused = decode_tf_message(by_hand)
    assert refused == [] and kept == [st("odom", "base_link", 12.5, (1.0, 2.0, 0.0), q)]


def test_a_tfmessage_from_rosbags_decodes_to_its_transforms_and_keys_are_rmw_zenohs() -> None:
    types = ros.typestore().types
    vector, quaternion = types["geometry_msgs/msg/Vector3"], types["geometry_msgs/msg/Quaternion"]
    stamped = [
        types["geometry_msgs/msg/TransformStamped"](
            header=ros.make_header(3.25, "/base_link"),  # tf2 strips a leading slash
            child_frame_id=f"cam{k}_optical_frame",
            transform=types["geometry_msgs/msg/Transform"](
                translation=vector(x=0.1 * k, y=-0.2, z=1.5), rotation=quaternion(x=0.0, y=0.0, z=0.0, w=1.0)
            ),
        )
        for k in range(3)
    ]
    payload = bytes(ros.typestore().serialize_cdr(types[TF_MESSAGE](transforms=stamped), TF_MESSAGE))
    kept, refused = decode_tf_message(payload)
    assert refused == []
    assert [(t.parent, t.child, t.stamp) for t in kept] == [
        ("base_link", f"cam{k}_optical_frame", 3.25) for k in range(3)
    ]
    assert kept[2].transform.translation == pytest.approx((0.2, -0.2, 1.5))
    assert ros.type_hash(TF_MESSAGE) == TF_HASH
    for topic in ("/tf", "/tf_static"):
        key = ros.topic_key(ros.RosTopic(topic, TF_MESSAGE, "rmw_zenoh"))
        assert key == f"0{topic}/tf2_msgs::msg::dds_::TFMessage_/{TF_HASH}"
        assert ros.parse_key(key, "rmw_zenoh").msgtype == TF_MESSAGE
        assert ros.topic_key(ros.RosTopic(topic, TF_MESSAGE, "bridge")) == topic[1:]


@pytest.mark.parametrize(
    ("bad", "reason"),
    [
        (st("base_link", "base_link", 1.0), "tf_self_transform"),
        (st("", "cam", 1.0), "tf_no_frame_id"),
        (st("base_link", "", 1.0), "tf_no_frame_id"),
        (st("base_link", "cam", 1.0, (math.nan, 0.0, 0.0)), "tf_nan"),
        (st("base_link", "cam", 1.0, q=(0.0, 0.0, 0.0, 1.1)), "tf_denormalized_quaternion"),
        (st("base_link", "cam", 1.0, q=(0.0, 0.0, 0.0, 0.0)), "tf_denormalized_quaternion"),
        (st("base_link", "c" * 300, 1.0), "tf_frame_id_too_long"),
    ],
)
def test_a_transform_tf2_would_ignore_is_refused_with_its_reason_and_the_rest_kept(
    bad: StampedTransform, reason: str
) -> None:
    good = st("odom", "base_link", 1.0, (1.0, 0.0, 0.0))
    kept, refused = decode_tf_message(tf_message_cdr([good, bad]))
    assert kept == [good] and [r.reason for r in refused] == [reason]


def test_a_quaternion_slightly_off_unit_is_normalised_and_garbage_is_bad_tf() -> None:
    kept, _ = decode_tf_message(tf_message_cdr([st("a", "b", 0.0, q=(0.0, 0.0, 0.0, 1.004))]))
    assert kept[0].transform.rotation == pytest.approx((0.0, 0.0, 0.0, 1.0))
    for payload in (b"", b"\x00\x01\x00\x00\xff\xff\xff\x7f", tf_message_cdr([st("a", "b", 0.0)])[:-9]):
        with pytest.raises(RejectedInput) as err:
            decode_tf_message(payload)
        assert err.value.reason == "bad_tf"


def test_composition_and_inverse_match_homogeneous_matrices() -> None:
    rng = np.random.default_rng(3)

    def random_transform() -> Transform:
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        return Transform(tuple(rng.normal(size=3)), tuple(q))  # type: ignore[arg-type]

    def homogeneous(t: Transform) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = t.matrix(), t.translation
        return m

    a, b = random_transform(), random_transform()
    assert homogeneous(a.then(b)) == pytest.approx(homogeneous(a) @ homogeneous(b))
    assert homogeneous(a.inverse()) == pytest.approx(np.linalg.inv(homogeneous(a)))
    assert np.linalg.det(a.matrix()) == pytest.approx(1.0)
    # slerp takes the shorter arc: from yaw 170 deg to -170 deg through 180, not through 0
    half = interpolate(Transform(rotation=yaw_q(math.radians(170))), Transform(rotation=yaw_q(math.radians(-170))), 0.5)
    assert abs(half.yaw()) == pytest.approx(math.pi)


def static_robot(tree: TransformTree) -> None:
    """base_link -> camera_link (1.0 m up, pitched down 0.3) -> camera_optical_frame (the optical rotation)."""
    pitch = (0.0, math.sin(0.15), 0.0, math.cos(0.15))
    tree.add(st("base_link", "camera_link", 0.0, (0.2, 0.0, 1.0), pitch), static=True)
    tree.add(st("camera_link", "camera_optical_frame", 0.0, q=(-0.5, 0.5, -0.5, 0.5)), static=True)


def test_a_chain_of_static_links_gives_the_camera_mount_in_either_axis_convention() -> None:
    tree = TransformTree()
    static_robot(tree)
    optical = tree.lookup("base_link", "camera_optical_frame")
    assert tree.latest_common_time("base_link", "camera_optical_frame") is None  # static: any stamp
    from_optical = mount_from_axes(np.array(optical.translation), optical.matrix(), optical=True)
    body = tree.lookup("base_link", "camera_link", stamp=123.0)
    from_body = mount_from_axes(np.array(body.translation), body.matrix(), optical=False)
    expected = CameraMount(x=0.2, y=0.0, z=1.0, pitch=0.3)
    for mount in (from_optical, from_body):
        assert (mount.x, mount.y, mount.z, mount.roll, mount.pitch, mount.yaw) == pytest.approx(
            (0.2, 0.0, 1.0, 0.0, 0.3, 0.0), abs=1e-9
        )
        assert mount.rotation_optical == pytest.approx(expected.rotation_optical)
    # and the optical frame's axes are the mount's optical rotation: z forward (tilted down), x right, y down
    assert optical.matrix() == pytest.approx(expected.rotation_optical)


def test_any_mount_survives_the_round_trip_through_an_optical_frame() -> None:
    mount = CameraMount(x=0.3, y=-0.1, z=0.8, roll=0.05, pitch=0.4, yaw=-0.7)
    back = mount_from_axes(mount.origin, mount.rotation_optical, optical=True)
    assert (back.roll, back.pitch, back.yaw) == pytest.approx((0.05, 0.4, -0.7))


def test_a_dynamic_link_is_interpolated_at_the_stamp_and_never_extrapolated() -> None:
    tree = TransformTree(buffer_s=10.0)
    tree.add(st("odom", "base_link", 10.0, (0.0, 0.0, 0.0), yaw_q(0.0)), static=False)
    tree.add(st("odom", "base_link", 11.0, (1.0, 0.0, 0.0), yaw_q(0.4)), static=False)
    mid = tree.lookup("odom", "base_link", 10.25)
    assert mid.translation == pytest.approx((0.25, 0.0, 0.0)) and mid.yaw() == pytest.approx(0.1)
    assert tree.lookup("odom", "base_link").translation == pytest.approx((1.0, 0.0, 0.0))  # latest
    with pytest.raises(TfLookupError) as err:
        tree.lookup("odom", "base_link", 11.5)
    assert err.value.reason == "tf_extrapolation_future"
    with pytest.raises(TfLookupError) as err:
        tree.lookup("odom", "base_link", 9.0)
    assert err.value.reason == "tf_extrapolation_past"


def test_samples_out_of_order_give_the_same_lookups_and_old_ones_are_refused() -> None:
    samples = [st("odom", "base_link", 10.0 + 0.1 * k, (0.1 * k, 0.0, 0.0), yaw_q(0.05 * k)) for k in range(20)]
    in_order, shuffled = TransformTree(buffer_s=5.0), TransformTree(buffer_s=5.0)
    for sample in samples:
        in_order.add(sample, static=False)
    for k in np.random.default_rng(0).permutation(len(samples)):
        shuffled.add(samples[k], static=False)
    for stamp in (10.0, 10.55, 11.23, 11.9):
        assert shuffled.lookup("odom", "base_link", stamp) == in_order.lookup("odom", "base_link", stamp)
    with pytest.raises(RejectedInput) as err:
        in_order.add(st("odom", "base_link", 6.8), static=False)  # 5.1 s before the newest (11.9)
    assert err.value.reason == "tf_old_data"
    in_order.add(st("odom", "base_link", 30.0, (3.0, 0.0, 0.0)), static=False)  # the buffer slides
    with pytest.raises(TfLookupError):
        in_order.lookup("odom", "base_link", 11.0)


def test_a_missing_link_or_an_unknown_frame_is_an_error_naming_it() -> None:
    tree = TransformTree()
    static_robot(tree)
    with pytest.raises(TfLookupError) as err:
        tree.lookup("odom", "camera_optical_frame", 1.0)  # odom never seen
    assert err.value.reason == "tf_unknown_frame" and "'odom'" in err.value.detail
    tree.add(st("odom", "base_footprint", 1.0), static=False)  # base_footprint -> base_link is missing
    with pytest.raises(TfLookupError) as err:
        tree.lookup("odom", "camera_optical_frame", 1.0)
    assert err.value.reason == "tf_no_chain" and "'base_link'" in err.value.detail
    tree.add(st("base_footprint", "base_link", 0.0, (0.0, 0.0, 0.1)), static=True)  # the link arrives
    assert tree.lookup("odom", "camera_link", 1.0).translation == pytest.approx((0.2, 0.0, 1.1))


def test_the_latest_common_time_of_two_dynamic_links_is_the_older_newest() -> None:
    tree = TransformTree()
    for k in range(5):
        tree.add(st("map", "odom", 1.0 + k, (0.0, 0.1 * k, 0.0)), static=False)
        tree.add(st("odom", "base_link", 1.0 + k + 0.5, (float(k), 0.0, 0.0)), static=False)
    assert tree.latest_common_time("map", "base_link") == pytest.approx(5.0)
    assert tree.lookup("map", "base_link").translation == pytest.approx((3.5, 0.4, 0.0))


def test_invented_frames_cannot_grow_the_tree_without_bound() -> None:
    tree = TransformTree()
    for k in range(MAX_FRAMES):
        tree.add(st("base_link", f"f{k}", 0.0), static=True)
    with pytest.raises(RejectedInput) as err:
        tree.add(st("base_link", "one_more", 0.0), static=True)
    assert err.value.reason == "tf_too_many_frames"
    tree.add(st("base_link", "f3", 0.0, (1.0, 0.0, 0.0)), static=True)  # a known frame is still updated
    assert tree.lookup("base_link", "f3").translation == (1.0, 0.0, 0.0)
