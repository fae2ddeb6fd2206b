"""ROS 2's own typesupport as the reference for every message gcdtrav writes or reads over rmw_zenoh.

gcdtrav encodes and decodes CDR without ROS (rosbags in service/ros/, numpy in schemas/ros_image.py). Here
ROS 2 Kilted's rclpy.serialization (Fast CDR, the wheels of tests/requirements-ros2.txt) reads what we write
and writes what we read. CDR leaves padding bytes unspecified, so messages are compared, never raw bytes. The
RIHS01 hashes we put in rmw_zenoh keys and liveliness tokens are compared with the type descriptions the
message packages install (share/<pkg>/msg/<Type>.json); for the types without a wheel (TFMessage, GridMap) ROS
2's generator computes them from the upstream .msg files in tests/ros2/upstream_msg/.
"""

from __future__ import annotations

import json
import math
import os
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from gcdtrav.schemas import ros_image, ros_nav
from gcdtrav.schemas.limits import MAX_FRAME_ID_CHARS
from gcdtrav.schemas.messages import GridHeader
from gcdtrav.service.ros import cdr, tf
from gcdtrav.service.ros.grid_map_msgs import GRID_MAP
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from real_components import require_rclpy

from tools import ros_fixtures

UPSTREAM_MSG = Path(__file__).parent / "upstream_msg"
# A loaded CI host runs examples slowly: bound them by count, never by time
EXAMPLES = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

frame_ids = st.one_of(
    st.just(""),
    st.text(st.characters(codec="utf-8", exclude_characters="\x00"), max_size=12),
    st.integers(MAX_FRAME_ID_CHARS - 1, MAX_FRAME_ID_CHARS).map(lambda n: "f" * n),  # the longest we keep
)
secs = st.integers(-(2**31), 2**31 - 1)
nanosecs = st.integers(0, 999_999_999)
finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


@pytest.fixture(autouse=True)
def _rclpy() -> None:
    require_rclpy()


def serialize(message: Any) -> bytes:
    from rclpy.serialization import serialize_message

    return bytes(serialize_message(message))


def deserialize(payload: bytes, message_type: type) -> Any:
    from rclpy.serialization import deserialize_message

    return deserialize_message(payload, message_type)


def official_header(sec: int, nanosec: int, frame_id: str) -> Any:
    from builtin_interfaces.msg import Time
    from std_msgs.msg import Header

    return Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame_id)


def assert_header(header: Any, sec: int, nanosec: int, frame_id: str) -> None:
    assert (header.stamp.sec, header.stamp.nanosec, header.frame_id) == (sec, nanosec, frame_id)


# ---- RIHS01 type hashes ---------------------------------------------------------------------------------


def package_share(package: str) -> Path:
    """A ROS 2 package's share directory: in the prefix the wheels installed into (a venv's or the base one)."""
    prefixes = [sys.prefix, sys.base_prefix, *filter(None, os.environ.get("AMENT_PREFIX_PATH", "").split(":"))]
    for prefix in prefixes:
        if (Path(prefix) / "share" / package / "msg").is_dir():
            return Path(prefix) / "share" / package
    raise AssertionError(f"no share/{package}/msg under {prefixes}")


def installed_type_description(msgtype: str) -> dict[str, Any]:
    """The type description JSON a ROS 2 message package installs (rosidl_generator_type_description's output)."""
    package, _, name = msgtype.split("/")
    return dict(json.loads((package_share(package) / "msg" / f"{name}.json").read_text()))


@pytest.mark.parametrize(
    "msgtype",
    [
        cdr.IMAGE,
        cdr.COMPRESSED_IMAGE,
        "sensor_msgs/msg/CameraInfo",
        "nav_msgs/msg/Odometry",
        cdr.OCCUPANCY_GRID,
        "geometry_msgs/msg/Twist",
    ],
)
def test_our_type_hash_is_the_one_the_installed_package_describes(msgtype: str) -> None:
    description = installed_type_description(msgtype)
    (own,) = [entry for entry in description["type_hashes"] if entry["type_name"] == msgtype]
    assert cdr.type_hash(msgtype) == own["hash_string"]


def generated_type_hashes(package: str, msg_dir: Path, tmp_path: Path) -> dict[str, str]:
    """RIHS01 hashes from .msg files, by ROS 2's own pipeline: rosidl_adapter (.msg -> .idl), then
    rosidl_generator_type_description with the installed packages' descriptions for the types they use."""
    from rosidl_adapter.msg import convert_msg_to_idl
    from rosidl_generator_type_description import generate_type_hash

    source = tmp_path / package
    (source / "msg").mkdir(parents=True)
    idl_tuples = []
    for msg_file in sorted(msg_dir.glob("*.msg")):
        (source / "msg" / msg_file.name).write_text(msg_file.read_text())
        convert_msg_to_idl(source, package, Path("msg") / msg_file.name, source / "msg")
        idl_tuples.append(f"{source}:msg/{msg_file.stem}.idl")
    include_paths = [f"{dependency}:{package_share(dependency)}" for dependency in ("std_msgs", "geometry_msgs")]
    arguments = tmp_path / "arguments.json"
    arguments.write_text(
        json.dumps(
            {
                "package_name": package,
                "output_dir": str(tmp_path / "out"),
                "idl_tuples": idl_tuples,
                "include_paths": include_paths,
            }
        )
    )
    hashes = {}
    for generated in generate_type_hash(str(arguments)):
        own = json.loads(Path(generated).read_text())["type_hashes"][0]
        hashes[own["type_name"]] = own["hash_string"]
    return hashes


@pytest.mark.parametrize(
    ("package", "msgtypes"),
    [("tf2_msgs", [tf.TF_MESSAGE]), ("grid_map_msgs", [GRID_MAP, "grid_map_msgs/msg/GridMapInfo"])],
)
def test_our_type_hash_of_a_type_without_a_wheel_is_the_one_ros2_generates(
    package: str, msgtypes: list[str], tmp_path: Path
) -> None:
    generated = generated_type_hashes(package, UPSTREAM_MSG / package, tmp_path)
    assert {msgtype: cdr.type_hash(msgtype) for msgtype in msgtypes} == {m: generated[m] for m in msgtypes}


# ---- images: what the service publishes, what cameras send it ------------------------------------------


@given(
    shape=st.tuples(st.integers(1, 6), st.integers(1, 6)),
    sec=secs,
    nanosec=nanosecs,
    frame_id=frame_ids,
    seed=st.integers(0, 2**32 - 1),
)
@EXAMPLES
def test_the_official_side_reads_our_images_as_the_same_message(
    shape: tuple[int, int], sec: int, nanosec: int, frame_id: str, seed: int
) -> None:
    from sensor_msgs.msg import CompressedImage, Image

    rng = np.random.default_rng(seed)
    header = cdr.header_of(sec, nanosec, frame_id)
    values = rng.normal(size=shape).astype(np.float32)
    values[0, 0] = np.nan  # "no estimate" patches travel as NaN
    rgb = rng.integers(0, 256, (*shape, 3), dtype=np.uint8)

    float_image = deserialize(cdr.float_image_cdr(header, values), Image)
    assert_header(float_image.header, sec, nanosec, frame_id)
    assert (float_image.height, float_image.width, float_image.encoding) == (*shape, "32FC1")
    assert (float_image.is_bigendian, float_image.step) == (0, shape[1] * 4)
    np.testing.assert_array_equal(np.frombuffer(bytes(float_image.data), "<f4").reshape(shape), values)

    rgb_image = deserialize(cdr.rgb_image_cdr(header, rgb), Image)
    assert_header(rgb_image.header, sec, nanosec, frame_id)
    assert (rgb_image.height, rgb_image.width, rgb_image.encoding, rgb_image.step) == (*shape, "rgb8", shape[1] * 3)
    assert bytes(rgb_image.data) == rgb.tobytes()

    jpeg = bytes(rng.integers(0, 256, int(rng.integers(0, 64)), dtype=np.uint8))  # opaque to CDR
    preview = deserialize(cdr.compressed_jpeg_cdr(header, jpeg), CompressedImage)
    assert_header(preview.header, sec, nanosec, frame_id)
    assert (preview.format, bytes(preview.data)) == (cdr.PREVIEW_FORMAT, jpeg)


@given(
    shape=st.tuples(st.integers(1, 6), st.integers(1, 6)),
    encoding=st.sampled_from(["rgb8", "bgr8", "rgba8", "bgra8", "mono8"]),
    stamp=st.floats(0, 2e9),
    frame_id=frame_ids,
    seed=st.integers(0, 2**32 - 1),
)
@EXAMPLES
def test_the_official_side_reads_the_camera_images_our_tests_send(
    shape: tuple[int, int], encoding: str, stamp: float, frame_id: str, seed: int
) -> None:
    """tools/ros_fixtures.py's writers stand in for camera drivers in tests, benchmarks and examples."""
    from sensor_msgs.msg import CompressedImage, Image

    channels = ros_image.RAW_ENCODINGS[encoding]
    pixels = np.random.default_rng(seed).integers(0, 256, (*shape, channels), dtype=np.uint8)
    image = deserialize(ros_fixtures.image_cdr(pixels, stamp, frame_id, encoding), Image)
    assert image.header.frame_id == frame_id
    assert abs(image.header.stamp.sec + image.header.stamp.nanosec * 1e-9 - stamp) < 1e-6
    assert (image.height, image.width, image.encoding, image.step) == (*shape, encoding, shape[1] * channels)
    assert bytes(image.data) == pixels.tobytes()

    payload = ros_fixtures.compressed_image_cdr(b"\xff\xd8jpeg", stamp, frame_id, "png")
    compressed = deserialize(payload, CompressedImage)
    assert (compressed.header.frame_id, compressed.format, bytes(compressed.data)) == (frame_id, "png", b"\xff\xd8jpeg")


def expected_rgb(data: np.ndarray, height: int, width: int, step: int, encoding: str, big_endian: int) -> np.ndarray:
    """What cv_bridge shows for an image of these bytes (row padding dropped), written out per encoding."""
    channels = ros_image.RAW_ENCODINGS[encoding]
    pixels = data.reshape(height, step)[:, : width * channels].reshape(height, width, channels)
    if encoding == "mono16":  # the most significant byte of each 16-bit value
        return np.repeat(pixels[:, :, [0 if big_endian else 1]], 3, axis=2)
    if encoding == "mono8":
        return np.repeat(pixels, 3, axis=2)
    return pixels[:, :, [2, 1, 0]] if encoding.startswith("bgr") else pixels[:, :, :3]


@given(
    shape=st.tuples(st.integers(1, 6), st.integers(1, 6)),
    encoding=st.sampled_from(["rgb8", "bgr8", "rgba8", "bgra8", "mono8", "mono16"]),
    row_padding=st.integers(0, 5),
    big_endian=st.integers(0, 1),
    sec=secs,
    nanosec=nanosecs,
    frame_id=frame_ids,
    seed=st.integers(0, 2**32 - 1),
)
@EXAMPLES
def test_we_read_an_official_image_exactly(
    shape: tuple[int, int],
    encoding: str,
    row_padding: int,
    big_endian: int,
    sec: int,
    nanosec: int,
    frame_id: str,
    seed: int,
) -> None:
    from sensor_msgs.msg import Image

    height, width = shape
    step = width * ros_image.RAW_ENCODINGS[encoding] + row_padding
    data = np.random.default_rng(seed).integers(0, 256, height * step, dtype=np.uint8)
    message = Image(
        header=official_header(sec, nanosec, frame_id),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=big_endian,
        step=step,
        data=data.tobytes(),
    )
    payload = serialize(message)
    ours = ros_image.decode_ros_image(payload, cdr.IMAGE, max_pixels=height * width)
    assert (ours.sec, ours.nanosec, ours.frame_id) == (sec, nanosec, frame_id)
    np.testing.assert_array_equal(ours.image, expected_rgb(data, height, width, step, encoding, big_endian))
    assert ros_image.peek_stamp(payload) == pytest.approx(sec + nanosec * 1e-9)
    # Fast CDR writes the host's order; a big-endian robot's payload (encapsulation CDR_BE) reads the same
    store = cdr.typestore()
    big = bytes(store.serialize_cdr(store.deserialize_cdr(payload, cdr.IMAGE), cdr.IMAGE, little_endian=False))
    assert big[:2] == b"\x00\x00"
    from_big = ros_image.decode_ros_image(big, cdr.IMAGE, max_pixels=height * width)
    assert (from_big.sec, from_big.nanosec, from_big.frame_id) == (sec, nanosec, frame_id)
    np.testing.assert_array_equal(from_big.image, ours.image)


def test_we_read_an_official_image_without_pixels_as_refused_not_crashed() -> None:
    from sensor_msgs.msg import Image

    payload = serialize(Image(encoding="rgb8"))  # the default message: 0 x 0, an empty data array
    with pytest.raises(ros_image.RejectedInput) as refused:
        ros_image.decode_ros_image(payload, cdr.IMAGE, max_pixels=100)
    assert refused.value.reason == "size_mismatch"


@given(
    shape=st.tuples(st.integers(1, 5), st.integers(1, 5)),
    encoding=st.sampled_from(["32FC1", "16UC1", "mono16"]),
    big_endian=st.integers(0, 1),
    row_padding=st.sampled_from([0, 4]),
    seed=st.integers(0, 2**32 - 1),
)
@EXAMPLES
def test_we_read_an_official_depth_image_exactly(
    shape: tuple[int, int], encoding: str, big_endian: int, row_padding: int, seed: int
) -> None:
    from sensor_msgs.msg import Image

    rng = np.random.default_rng(seed)
    height, width = shape
    order = ">" if big_endian else "<"
    if encoding == "32FC1":
        metres = rng.uniform(0, 50, shape).astype(np.float32)
        raw, expected = metres.astype(order + "f4"), metres
    else:
        millimetres = rng.integers(0, 65536, shape).astype(np.uint16)
        raw, expected = millimetres.astype(order + "u2"), millimetres.astype(np.float32) * np.float32(1e-3)
    rows = np.zeros((height, raw.itemsize * width + row_padding), np.uint8)
    rows[:, : raw.itemsize * width] = raw.view(np.uint8).reshape(height, -1)
    message = Image(
        header=official_header(7, 8, "depth_optical"),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=big_endian,
        step=rows.shape[1],
        data=rows.tobytes(),
    )
    np.testing.assert_array_equal(cdr.decode_depth(serialize(message)), expected)


@given(
    image_format=st.sampled_from(["jpeg", "png", "rgb8; jpeg compressed bgr8", "bgr8; png compressed bgr8"]),
    sec=secs,
    nanosec=nanosecs,
    frame_id=frame_ids,
    seed=st.integers(0, 2**32 - 1),
)
@EXAMPLES
def test_we_read_an_official_compressed_image_exactly(
    image_format: str, sec: int, nanosec: int, frame_id: str, seed: int
) -> None:
    from sensor_msgs.msg import CompressedImage

    rgb = np.random.default_rng(seed).integers(0, 256, (5, 7, 3), dtype=np.uint8)
    ok, encoded = cv2.imencode(".png", rgb[:, :, ::-1])  # lossless: the pixels must come back exactly
    assert ok
    message = CompressedImage(
        header=official_header(sec, nanosec, frame_id), format=image_format, data=encoded.tobytes()
    )
    ours = ros_image.decode_ros_image(serialize(message), cdr.COMPRESSED_IMAGE, max_pixels=35)
    assert (ours.sec, ours.nanosec, ours.frame_id) == (sec, nanosec, frame_id)
    np.testing.assert_array_equal(ours.image, rgb)


# ---- the ground grid's inputs and outputs ---------------------------------------------------------------


@given(
    fx=st.floats(1e-3, 1e5),
    fy=st.floats(1e-3, 1e5),
    cx=finite,
    cy=finite,
    size=st.tuples(st.integers(1, 2**32 - 1), st.integers(1, 2**32 - 1)),
    distortion=st.lists(finite, max_size=14),  # plumb_bob 5, rational_polynomial 8, or none
    frame_id=frame_ids,
)
@EXAMPLES
def test_we_read_an_official_camera_info_exactly(
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    size: tuple[int, int],
    distortion: list[float],
    frame_id: str,
) -> None:
    from sensor_msgs.msg import CameraInfo, RegionOfInterest

    width, height = size
    message = CameraInfo(
        header=official_header(3, 4, frame_id),
        height=height,
        width=width,
        distortion_model="plumb_bob" if distortion else "",
        d=distortion,
        k=[fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0],
        r=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        p=[fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0],
        binning_x=2,
        binning_y=3,
        roi=RegionOfInterest(x_offset=1, y_offset=2, height=3, width=4, do_rectify=True),
    )
    camera, camera_frame = cdr.decode_camera_info_frame(serialize(message))
    assert (camera.fx, camera.fy, camera.cx, camera.cy) == (fx, fy, cx, cy)
    assert (camera.width, camera.height, camera_frame) == (width, height, frame_id)


def unit_quaternion(values: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
    norm = math.sqrt(sum(v * v for v in values))
    x, y, z, w = (v / norm for v in values)
    return x, y, z, w


quaternions = st.tuples(*[st.floats(-1, 1)] * 4).filter(lambda q: sum(v * v for v in q) > 1e-3).map(unit_quaternion)
velocities = st.floats(-1e3, 1e3)


@given(
    sec=st.integers(0, 2**31 - 1),
    nanosec=nanosecs,
    frame_id=frame_ids,
    position=st.tuples(st.floats(-1e6, 1e6), st.floats(-1e6, 1e6), st.floats(-1e3, 1e3)),
    q=quaternions,
    twist=st.tuples(velocities, velocities, velocities, velocities, velocities, velocities),
    seed=st.integers(0, 2**32 - 1),
)
@EXAMPLES
def test_we_read_official_odometry_exactly(
    sec: int,
    nanosec: int,
    frame_id: str,
    position: tuple[float, float, float],
    q: tuple[float, float, float, float],
    twist: tuple[float, ...],
    seed: int,
) -> None:
    from geometry_msgs.msg import Point, Pose, PoseWithCovariance, Quaternion, Twist, TwistWithCovariance, Vector3
    from nav_msgs.msg import Odometry

    covariance = np.random.default_rng(seed).normal(size=36)
    message = Odometry(
        header=official_header(sec, nanosec, frame_id),
        child_frame_id="base_link",
        pose=PoseWithCovariance(
            pose=Pose(
                position=Point(x=position[0], y=position[1], z=position[2]),
                orientation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]),
            ),
            covariance=covariance,
        ),
        twist=TwistWithCovariance(
            twist=Twist(
                linear=Vector3(x=twist[0], y=twist[1], z=twist[2]), angular=Vector3(x=twist[3], y=twist[4], z=twist[5])
            ),
            covariance=covariance,
        ),
    )
    odometry = ros_nav.odometry_motion(serialize(message))  # the service's and the relay's one reader
    assert (odometry.frame_id, odometry.x, odometry.y) == (frame_id or "odom", position[0], position[1])  # unset: odom
    assert odometry.stamp == sec + nanosec * 1e-9
    assert odometry.yaw == ros_nav.yaw_of_quaternion(*q)
    assert (odometry.vx, odometry.vy, odometry.wz) == (twist[0], twist[1], twist[5])
    assert cdr.decode_pose(serialize(message), "odometry") == ros_nav.odometry_pose(serialize(message))


@given(
    stamp=st.floats(0, 2e9),
    x=st.floats(-1e6, 1e6),
    y=st.floats(-1e6, 1e6),
    yaw=st.floats(-math.pi, math.pi),
    twist=st.tuples(velocities, velocities, velocities),
)
@EXAMPLES
def test_the_official_side_reads_our_odometry_and_twist_as_the_same_message(
    stamp: float, x: float, y: float, yaw: float, twist: tuple[float, float, float]
) -> None:
    """Simulated robots, tests and benchmarks send these (tools/ros_fixtures.py); the service reads Twist from
    /cmd_vel."""
    from geometry_msgs.msg import Twist
    from nav_msgs.msg import Odometry

    odometry = deserialize(ros_fixtures.odometry_cdr(stamp, x, y, yaw, *twist), Odometry)
    header = cdr.make_header(stamp, "odom")
    assert_header(odometry.header, header.stamp.sec, header.stamp.nanosec, "odom")
    assert odometry.child_frame_id == "base_link"
    pose = odometry.pose.pose
    assert (pose.position.x, pose.position.y, pose.position.z) == (x, y, 0.0)
    orientation = (pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w)
    assert orientation == (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))
    moving = odometry.twist.twist
    assert (moving.linear.x, moving.linear.y, moving.angular.z) == twist
    assert not odometry.pose.covariance.any() and not odometry.twist.covariance.any()

    command = deserialize(ros_fixtures.twist_cdr(*twist), Twist)
    assert (command.linear.x, command.linear.y, command.linear.z) == (twist[0], twist[1], 0.0)
    assert (command.angular.x, command.angular.y, command.angular.z) == (0.0, 0.0, twist[2])


@given(linear=st.tuples(velocities, velocities, velocities), angular=st.tuples(velocities, velocities, velocities))
@EXAMPLES
def test_we_read_an_official_twist_exactly(
    linear: tuple[float, float, float], angular: tuple[float, float, float]
) -> None:
    from geometry_msgs.msg import Twist, Vector3

    message = Twist(
        linear=Vector3(x=linear[0], y=linear[1], z=linear[2]), angular=Vector3(x=angular[0], y=angular[1], z=angular[2])
    )
    command = ros_nav.twist_command(serialize(message), stamped=False)
    assert (command.vx, command.vy, command.wz) == (linear[0], linear[1], angular[2])


def grid_header(stamp: float, frame_id: str, origin: tuple[float, float], resolution: float, cells: int) -> GridHeader:
    return GridHeader(
        source="cam",
        seq=1,
        stamp=stamp,
        frame_id=frame_id,
        origin=origin,
        resolution=resolution,
        cells=cells,
        anchor_set_version="v1",
        resets=0,
        known_cells=0,
        instance="test",
    )


@given(
    cells=st.integers(1, 12),
    resolution=st.floats(1e-3, 10),
    origin=st.tuples(st.floats(-1e5, 1e5), st.floats(-1e5, 1e5)),
    stamp=st.floats(0, 2e9),
    frame_id=frame_ids.filter(lambda f: f != ""),
    seed=st.integers(0, 2**32 - 1),
)
@EXAMPLES
def test_the_official_side_reads_our_occupancy_grid_as_the_same_message(
    cells: int, resolution: float, origin: tuple[float, float], stamp: float, frame_id: str, seed: int
) -> None:
    from nav_msgs.msg import OccupancyGrid

    rng = np.random.default_rng(seed)
    values = rng.uniform(0, 1, (cells, cells))
    known = rng.uniform(size=(cells, cells)) < 0.7
    header = grid_header(stamp, frame_id, origin, resolution, cells)
    grid = deserialize(cdr.occupancy_cdr(header, values, known), OccupancyGrid)
    ros_header = cdr.make_header(stamp, frame_id)
    assert_header(grid.header, ros_header.stamp.sec, ros_header.stamp.nanosec, frame_id)
    info = grid.info
    assert (info.map_load_time.sec, info.map_load_time.nanosec) == (ros_header.stamp.sec, ros_header.stamp.nanosec)
    assert (info.resolution, info.width, info.height) == (np.float32(resolution), cells, cells)
    assert (info.origin.position.x, info.origin.position.y, info.origin.position.z) == (*origin, 0.0)
    orientation = info.origin.orientation
    assert (orientation.x, orientation.y, orientation.z, orientation.w) == (0.0, 0.0, 0.0, 1.0)
    expected = np.where(known, np.round(values * 100), -1).astype(np.int8).ravel()
    np.testing.assert_array_equal(np.asarray(grid.data, np.int8), expected)


def test_the_official_side_reads_our_empty_occupancy_grid() -> None:
    """A grid with no cell (an edge a Nav2 reader must still take): an empty data array."""
    from nav_msgs.msg import OccupancyGrid

    header = grid_header(1.5, "odom", (0.0, 0.0), 0.5, 0)
    grid = deserialize(cdr.occupancy_values_cdr(header, np.zeros(0, np.int8)), OccupancyGrid)
    assert (grid.info.width, grid.info.height, len(grid.data)) == (0, 0, 0)
