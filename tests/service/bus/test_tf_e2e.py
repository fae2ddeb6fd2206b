"""A grid's mount and pose from /tf_static and /tf over a real zenoh session on loopback, published as an rmw_zenoh
robot does (keys with the Jazzy type hash; /tf_static latched in an AdvancedPublisher's cache before the service
connects): the same cells as the same mount and poses typed in YAML."""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator

import numpy as np
import pytest
import zenoh
from gcdtrav.client.session.zenoh_args import zenoh_config
from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.schemas.keys import input_key
from gcdtrav.schemas.messages import Pose2D
from gcdtrav.schemas.settings import GridSettings
from gcdtrav.service.bus.entities import undeclare_all
from gcdtrav.service.bus.tf import declare_tf_inputs
from gcdtrav.service.runtime.grids import GridOutputs
from gcdtrav.service.runtime.history import FrameRecord
from gcdtrav.service.runtime.stats import ServiceStats
from zenoh import ext
from zenoh_helpers import connecting_config, free_port, subscribed_elsewhere, wait_until

pytest.importorskip("rosbags")

from gcdtrav.service.ros import cdr as ros
from gcdtrav.service.ros.tf import TF_MESSAGE, StampedTransform, Transform

from tools.ros_fixtures import tf_message_cdr

INTRINSICS = {"fx": 40, "fy": 40, "cx": 32, "cy": 24, "width": 64, "height": 48}
COMMON = {"source": "cam", "intrinsics": INTRINSICS, "size_m": 12.0, "resolution_m": 0.25}
PITCH = 0.35


def key(topic: str, layout: str) -> str:
    """A robot's TFMessage topic's key: rmw_zenoh's (domain 0, the Jazzy type hash) or zenoh-bridge-ros2dds's."""
    return ros.topic_key(ros.RosTopic(topic, TF_MESSAGE, layout))


def yaw_q(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def robot_static() -> bytes:
    """What robot_state_publisher latches: base_footprint -> base_link -> camera_link -> camera_optical_frame."""
    down = (0.0, math.sin(PITCH / 2), 0.0, math.cos(PITCH / 2))
    return tf_message_cdr(
        [
            StampedTransform("base_footprint", "base_link", 0.0, Transform((0.0, 0.0, 0.1))),
            StampedTransform("base_link", "camera_link", 0.0, Transform((0.3, 0.05, 0.8), down)),
            StampedTransform("camera_link", "camera_optical_frame", 0.0, Transform(rotation=(-0.5, 0.5, -0.5, 0.5))),
        ]
    )


def drive(stamp: float) -> tuple[float, float, float]:
    """The robot's odometry: 1 m/s, turning at 0.4 rad/s from the origin at t = 10 s."""
    t = stamp - 10.0
    yaw = 0.4 * t
    return (math.sin(yaw) / 0.4, (1 - math.cos(yaw)) / 0.4, yaw)


@pytest.fixture(params=["rmw_zenoh", "bridge"])
def robot_and_service(request: pytest.FixtureRequest) -> Iterator[tuple[zenoh.Session, zenoh.Session, str]]:
    layout = request.param
    port = free_port()
    listen = zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    if layout == "bridge":  # the bridge runs in a router, which stamps samples (its cache orders by timestamp)
        listen.insert_json5("timestamping/enabled", "true")
    robot = zenoh.open(listen)
    service: zenoh.Session | None = None
    try:
        # /tf_static (TRANSIENT_LOCAL, RELIABLE, depth 1), latched before the service exists: rmw_zenoh's publisher
        # caches and sends sporadic heartbeats; the bridge's only caches (route_publisher.rs)
        heartbeats = ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=0.5) if layout == "rmw_zenoh" else None
        static = ext.declare_advanced_publisher(
            robot,
            key("/tf_static", layout),
            cache=ext.CacheConfig(max_samples=1),
            sample_miss_detection=heartbeats,
            publisher_detection=True,
        )
        static.put(robot_static())
        service = zenoh.open(connecting_config(port))
        yield robot, service, layout
        static.undeclare()
    finally:
        if service is not None:
            service.close()
        robot.close()


def test_a_grid_from_tf_fuses_the_same_cells_as_the_same_mount_and_poses_in_yaml(robot_and_service) -> None:  # type: ignore[no-untyped-def]
    robot, session, layout = robot_and_service
    keys = {} if layout == "rmw_zenoh" else {"tf_key": "tf", "tf_static_key": "tf_static"}  # the defaults: rmw_zenoh
    typed = GridSettings.model_validate(
        COMMON | {"mount": {"x": 0.3, "y": 0.05, "z": 0.9, "pitch": PITCH}, "pose_key": "r/pose"}
    )
    from_tf = GridSettings.model_validate(
        COMMON | {"tf": {"mount": True, "pose": True, "base_frame": "base_footprint"} | keys}
    )
    count = len(default_anchor_set())
    yaml_grids, tf_grids = GridOutputs([typed], count, "yaml"), GridOutputs([from_tf], count, "tf")
    stats = ServiceStats(logging.getLogger("test"), 300.0)
    declared = declare_tf_inputs(session, tf_grids, stats)
    try:
        tf_camera, tree = tf_grids.sources["cam"].cameras["cam"], tf_grids.tf["cam"].tree
        assert wait_until(lambda: "camera_optical_frame" in tree, 60), "the latched /tf_static never arrived"
        assert tf_camera.mount_origin is None  # the camera's frame comes with its first image
        dynamic = robot.declare_publisher(key("/tf", layout), congestion_control=zenoh.CongestionControl.BLOCK)
        assert wait_until(lambda: dynamic.matching_status.matching, 60), "the service's /tf subscriber is unseen"
        stamps = [10.0 + 0.05 * k for k in range(61)]
        for stamp in stamps:
            x, y, yaw = drive(stamp)
            pose = Pose2D.validated({"stamp": stamp, "frame_id": "odom", "x": x, "y": y, "yaw": yaw})
            yaml_grids.set_pose("cam", pose.pack())
            odom = StampedTransform("odom", "base_footprint", stamp, Transform((x, y, 0.0), yaw_q(yaw)))
            dynamic.put(tf_message_cdr([odom]))
        dynamic.put(b"\x00\x01\x00\x00not a TFMessage")  # counted, nothing stops
        tf_poses = tf_grids.sources["cam"].poses
        assert wait_until(lambda: tf_poses.received == len(stamps) and stats.rejected_by_reason["bad_tf"] == 1, 60), (
            tf_poses.received,
            dict(stats.rejected_by_reason),
            tf_grids.tf["cam"].waiting,
        )
        dynamic.undeclare()

        anchors = default_anchor_set()
        logits = np.random.default_rng(1).normal(size=(len(anchors), 24, 32))
        weights = (np.exp(logits) / np.exp(logits).sum(axis=0)).astype(np.float32)  # a softmax per patch
        for stamp in (10.4, 11.02, 11.5, 12.9):  # between poses: interpolated alike in both grids
            record = FrameRecord(0, stamp, "camera_optical_frame", weights.astype(np.float16), anchors, (64, 48))
            fused = [grids.fuse("cam", record, weights) for grids in (yaml_grids, tf_grids)]
            assert fused[0] is not None and fused[1] is not None
        typed_grid, tf_grid = yaml_grids.sources["cam"].grid, tf_grids.sources["cam"].grid
        assert tf_grid.origin == pytest.approx(typed_grid.origin)
        assert typed_grid.known.sum() > 100 and np.array_equal(tf_grid.count, typed_grid.count)
        assert np.allclose(tf_grid.distributions(), typed_grid.distributions(), atol=1e-5, equal_nan=True)
        assert tf_grids.sources["cam"].frame_id() == "odom"
        mount = tf_camera.mount
        assert (mount.x, mount.y, mount.z, mount.pitch) == pytest.approx((0.3, 0.05, 0.9, PITCH))
    finally:
        undeclare_all(declared)


def test_the_service_fuses_a_grid_whose_mount_and_pose_come_from_the_robots_tf(tiny_backend, tmp_path) -> None:  # type: ignore[no-untyped-def]
    """The whole service: /tf streaming, a bare image (no frame id: the camera's tf frame is configured) not fused
    before /tf_static and the status saying why, fused at the pose from tf once it came, a bad message counted."""
    pytest.importorskip("torch")
    import threading
    import time

    from conftest import camera_grid, textured_image
    from gcdtrav.client import TraversabilityClient
    from gcdtrav.schemas.settings import ServiceSettings

    from tools.loopback import in_process_service

    grid = {k: v for k, v in camera_grid().items() if k not in ("mount", "pose_key")}
    grid |= {"tf": {"mount": True, "pose": True, "base_frame": "base_footprint"}, "frame_id": "camera_optical_frame"}
    settings = ServiceSettings.model_validate(
        {"state_dir": str(tmp_path), "instance": "tf", "preview": False, "grids": [grid], "reuse": {"enabled": False}}
    )
    with in_process_service(tiny_backend, settings) as (service, port):
        robot = zenoh.open(connecting_config(port))
        client = TraversabilityClient(config=connecting_config(port), timeout=5.0)
        stop = threading.Event()

        def odometry() -> None:  # the robot's /tf at 20 Hz, stamped by its clock (the frame's too: receipt time)
            publisher = robot.declare_publisher(key("/tf", "rmw_zenoh"))
            while not stop.wait(0.05):
                now = time.time()
                odom = StampedTransform("odom", "base_footprint", now, Transform((2.0, 1.0, 0.0), yaw_q(0.3)))
                publisher.put(tf_message_cdr([odom]))
            publisher.put(b"garbage")
            publisher.undeclare()

        streaming = threading.Thread(target=odometry, daemon=True)
        streaming.start()
        static = None
        try:
            state = service.runtime.grids.sources["cam"]
            assert service.ros_graph is not None  # no ros_inputs, but rmw_zenoh tf keys: the graph lists them
            assert wait_until(lambda: state.poses.received > 0, 60), "no pose from /tf"
            # the client's own session knows the service's input subscription: its one frame is not lost
            assert subscribed_elsewhere(client.session, input_key(client.input_prefix, "cam")), "the inputs"
            client.publish_image("cam", textured_image(60, 80))  # before /tf_static: no mount, and the status says why
            assert wait_until(lambda: state.health.not_fused.get("no_mount") == 1, 60), state.health
            (grid,) = client.status().grids or []
            assert grid.cameras["cam"].mount is None and grid.not_fused_by_reason == {"no_mount": 1}
            assert grid.cameras["cam"].placement is None  # a viewer draws no camera yet
            assert grid.tf_waiting["cam"].startswith("tf_unknown_frame") and "'camera_optical_frame'" in grid.problem
            static = ext.declare_advanced_publisher(
                robot, key("/tf_static", "rmw_zenoh"), cache=ext.CacheConfig(max_samples=1), publisher_detection=True,
                sample_miss_detection=ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=0.5),
            )  # fmt: skip
            static.put(robot_static())
            assert wait_until(lambda: "camera_optical_frame" in service.runtime.grids.tf["cam"].tree, 60)
            client.publish_image("cam", textured_image(60, 80, seed=1))
            assert wait_until(lambda: state.health.fused == 1, 60), state.health
            camera = state.cameras["cam"]
            assert camera.mount_origin == "tf" and camera.mount.z == pytest.approx(0.9)
            placement = (client.status().grids or [])[0].cameras["cam"].placement  # what a viewer draws
            assert placement is not None and (placement.x, placement.y, placement.z) == pytest.approx((0.3, 0.05, 0.9))
            assert placement.pitch == pytest.approx(PITCH) and placement.roll == pytest.approx(0.0, abs=1e-9)
            assert state.frame_id() == "odom" and state.fused_at is not None and state.fused_at.pose is not None
            assert (state.fused_at.pose.x, state.fused_at.pose.y) == pytest.approx((2.0, 1.0))
            stop.set()
            streaming.join(5)
            assert wait_until(lambda: client.status().rejected_by_reason.get("bad_tf") == 1, 60)
        finally:
            stop.set()
            if static is not None:
                static.undeclare()
            client.close()
            robot.close()
