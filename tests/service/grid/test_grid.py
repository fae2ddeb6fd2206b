"""Ground grid: projection by hand, fusion by hand, scrolling, resets, and end to end through zenoh."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from conftest import camera_grid, textured_image
from gcdtrav.schemas.anchors import Anchor, AnchorSet
from gcdtrav.service.grid.fusion import GridSpec, GroundGrid
from gcdtrav.service.grid.geometry import CameraMount, PinholeCamera, depth_points, ground_points

CAMERA = PinholeCamera(fx=500, fy=500, cx=320, cy=240, width=640, height=480)
HEIGHT, PITCH = 1.5, 0.3
MOUNT = CameraMount(z=HEIGHT, pitch=PITCH)


def project(u: float, v: float, mount: CameraMount = MOUNT, max_range: float = 100.0) -> tuple[np.ndarray, bool]:
    points, valid = ground_points(CAMERA, mount, np.array([u]), np.array([v]), max_range)
    return points[0], bool(valid[0])


def test_known_pixels_land_on_known_ground_points() -> None:
    ahead = HEIGHT / math.tan(PITCH)  # the optical axis meets the ground here
    point, valid = project(320, 240)
    assert valid and point == pytest.approx([ahead, 0.0], abs=1e-9)
    # 100 px right: optical ray (0.2, 0, 1) -> base direction (cos p, -0.2, -sin p)
    point, _ = project(420, 240)
    assert point == pytest.approx([ahead, -0.2 * HEIGHT / math.sin(PITCH)], abs=1e-9)
    # 60 px lower: depression p + atan(60 / 500)
    point, _ = project(320, 300)
    assert point == pytest.approx([HEIGHT / math.tan(PITCH + math.atan(60 / 500)), 0.0], abs=1e-9)
    shifted, _ = project(320, 240, CameraMount(x=0.5, y=-0.2, z=HEIGHT, pitch=PITCH))
    assert shifted == pytest.approx([ahead + 0.5, -0.2], abs=1e-9)
    turned, _ = project(320, 240, CameraMount(z=HEIGHT, pitch=PITCH, yaw=math.pi / 2))  # looking left
    assert turned == pytest.approx([0.0, ahead], abs=1e-9)


def test_pixels_above_the_horizon_or_too_far_are_left_out() -> None:
    horizon_row = 240 - 500 * math.tan(PITCH)  # about 85.4
    assert not project(320, horizon_row - 5)[1]
    assert not project(320, 0)[1]
    assert project(320, horizon_row + 5, max_range=1e6)[1]  # just below the horizon: very far, but ground
    assert not project(320, 240, max_range=4.0)[1]  # 4.84 m away
    assert project(320, 240, max_range=5.0)[1]


def test_depth_places_pixels_in_3d() -> None:
    depth = np.full((480, 640), 2.0, np.float32)
    depth[0, 0] = 0.0  # missing
    points, valid = depth_points(CAMERA, MOUNT, np.array([320.0, 0.0]), np.array([240.0, 0.0]), depth, 50.0)
    assert valid.tolist() == [True, False]
    assert points[0] == pytest.approx([2.0 * math.cos(PITCH), 0.0], abs=1e-9)


def anchor_set(*concepts: str) -> AnchorSet:
    return AnchorSet(anchors=[Anchor(concept=c, position=k / (len(concepts) - 1)) for k, c in enumerate(concepts)])


TWO = anchor_set("water", "road")
OLD, NEW = TWO, anchor_set("mud", "grass", "road")


def grid_2x2() -> GroundGrid:
    return GroundGrid(GridSpec(size_m=1.0, resolution_m=0.5, half_life_s=1.0), anchor_count=2, origin=(0.0, 0.0))


def test_fusion_over_two_frames_with_a_known_half_life() -> None:
    grid = grid_2x2()
    # frame 1 at t=0: two pixels in cell (0, 0), one all on anchor 0, one all on anchor 1
    grid.add(np.array([[0.1, 0.1], [0.2, 0.3]]), np.array([[1.0, 0.0], [0.0, 1.0]]), stamp=0.0, anchors=TWO)
    np.testing.assert_allclose(grid.cell_weights(0, 0), [0.5, 0.5])
    # frame 2 one half-life later: one pixel on anchor 0. (0.5 * (1, 1) + (1, 0)) / (0.5 * 2 + 1) = (0.75, 0.25)
    grid.add(np.array([[0.4, 0.4]]), np.array([[1.0], [0.0]]), stamp=1.0, anchors=TWO)
    np.testing.assert_allclose(grid.cell_weights(0, 0), [0.75, 0.25], atol=1e-6)
    assert grid.count[0, 0] == 3
    t, u, count = grid.layers(np.array([0.0, 1.0]), np.array([0.0, 0.0]))
    assert t[0, 0] == pytest.approx(0.25) and u[0, 0] == pytest.approx(math.sqrt(0.75 * 0.25))
    # unknown cells stay unknown
    assert grid.cell_weights(1, 1) is None and np.isnan(t[1, 1]) and np.isnan(u[0, 1]) and count[1, 0] == 0
    assert np.isnan(grid.distributions()[:, 1, 1]).all()
    # points outside the grid are ignored
    assert grid.add(np.array([[5.0, 5.0]]), np.array([[1.0], [0.0]]), stamp=1.0, anchors=TWO) == 0


def test_scrolling_by_whole_cells_keeps_content() -> None:
    grid = GroundGrid(GridSpec(size_m=2.0, resolution_m=0.5, half_life_s=10.0), anchor_count=2, origin=(0.0, 0.0))
    grid.add(np.array([[1.2, 0.7]]), np.array([[0.2], [0.8]]), stamp=0.0, anchors=TWO)  # cell (1, 2)
    grid.scroll_to((0.5, 0.0))  # the robot moved one cell along +x
    assert grid.origin == (0.5, 0.0)
    np.testing.assert_allclose(grid.cell_weights(1, 1), [0.2, 0.8])  # same place in the world, new index
    assert grid.count.sum() == 1
    grid.scroll_to((2.5, 0.0))  # beyond the grid: everything leaves, cells entering are unknown
    assert not grid.known.any()


def test_a_new_anchor_set_resets_the_grid() -> None:
    grid = grid_2x2()
    grid.add(np.array([[0.1, 0.1]]), np.array([[1.0], [0.0]]), stamp=0.0, anchors=OLD)
    grid.add(np.array([[0.6, 0.6]]), np.array([[0.0], [1.0], [0.0]]), stamp=0.1, anchors=NEW)
    assert grid.resets == 1 and f"from {OLD.version} to {NEW.version}" in grid.last_reset
    assert grid.cell_weights(0, 0) is None and grid.cell_weights(1, 1).tolist() == [0.0, 1.0, 0.0]


def test_path_cells_in_order() -> None:
    grid = GroundGrid(GridSpec(size_m=2.0, resolution_m=0.5), anchor_count=2, origin=(0.0, 0.0))
    assert grid.path_cells([(0.1, 0.1), (1.9, 0.1)]) == [(0, 0), (0, 1), (0, 2), (0, 3)]
    assert grid.path_cells([(0.1, 0.1), (0.1, 1.1), (-3.0, 1.1)]) == [(0, 0), (1, 0), (2, 0)]


# ---- end to end ----------------------------------------------------------------------------------------


def test_synthetic_drive_through_zenoh(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    pytest.importorskip("rosbags")
    from gcdtrav.client import Grid, TraversabilityClient
    from gcdtrav.client.commands.operator import status_table
    from gcdtrav.schemas.anchors import default_anchor_set
    from gcdtrav.schemas.keys import input_key
    from gcdtrav.schemas.messages import Pose2D
    from gcdtrav.schemas.settings import ServiceSettings
    from gcdtrav.service.ros import cdr as ros
    from zenoh_helpers import connecting_config, service_reachable, subscribed_elsewhere, wait_until

    from tools.loopback import in_process_service
    from tools.ros_fixtures import decode_grid_map

    settings = ServiceSettings.model_validate(
        {
            "state_dir": str(tmp_path),
            "instance": "grid-test",
            "max_frame_age_s": None,  # frames stamped 100 s after the epoch
            "preview": False,
            "grids": [camera_grid(max_range_m=6.0, half_life_s=5.0, occupancy_grid=True, grid_map=True, costmap=True)],
        }
    )
    with in_process_service(tiny_backend, settings) as (service, port):
        client = TraversabilityClient(config=connecting_config(port), timeout=5.0)
        grids: list[Grid] = []
        occupancy: list[bytes] = []
        grid_maps: list[bytes] = []
        costmaps: list[bytes] = []
        subscriptions = [
            client.subscribe_grid("cam", grids.append),
            client.session.declare_subscriber(
                "gcdtrav/out/cam/grid/occupancy", lambda s: occupancy.append(s.payload.to_bytes())
            ),
            client.session.declare_subscriber(
                "gcdtrav/out/cam/grid/gridmap", lambda s: grid_maps.append(s.payload.to_bytes())
            ),
            client.session.declare_subscriber(
                "gcdtrav/out/cam/grid/costmap", lambda s: costmaps.append(s.payload.to_bytes())
            ),
        ]

        def put_pose(pose: Pose2D) -> None:  # and wait until the service holds it: the next frame fuses at it
            held = service.status().grids[0].poses_held
            client.session.put("robot/pose", pose.pack())
            assert wait_until(lambda: service.status().grids[0].poses_held > held, 30), pose

        try:
            # the service's subscriptions known to the client (poses, images), the client's to the service
            assert wait_until(lambda: service_reachable(client), 60)
            for key in ("robot/pose", input_key(client.input_prefix, "cam")):
                assert subscribed_elsewhere(client.session, key), key
            for layer in ("", "occupancy", "gridmap", "costmap"):
                assert subscribed_elsewhere(service.session, service.keys.grid("cam", layer)), layer
            for step in range(3):  # drive 0.5 m along x per frame
                put_pose(Pose2D(stamp=100.0 + step, x=0.5 * step, y=0.0, yaw=0.0))
                client.publish_image("cam", textured_image(60, 80, seed=step), stamp=100.0 + step)
                assert wait_until(lambda n=step + 1: len(grids) >= n and len(occupancy) >= n, 60)
            grid = grids[-1]
            header = grid.header
            assert header.frame_id == "odom" and header.robot == (1.0, 0.0, 0.0) and header.seq == 2
            assert header.cells == 32 and header.resolution == 0.25
            assert header.origin == pytest.approx((1.0 - 4.0, -4.0))  # the robot at the centre
            assert header.known_cells > 0 and (grid.count > 0).sum() == header.known_cells
            assert np.isnan(grid.traversability[grid.count == 0]).all()
            # The camera looks forward: cells behind the robot are unknown, cells ahead known.
            assert grid.count[grid.cell_index(0.0, 0.0)] == 0 and grid.count[grid.cell_index(2.7, 0.0)] > 0
            cell = client.cell("cam", 2.7, 0.0)
            i, j = grid.cell_index(2.7, 0.0)
            assert cell.cell == (i, j) and cell.observations == grid.count[i, j]
            assert cell.patch is None and cell.seq is None and cell.grid_updates == header.seq  # no names that lie
            assert cell.mean == pytest.approx(grid.traversability[i, j], abs=2 / 65535)
            assert grid.match is not None and cell.match == pytest.approx(grid.match[i, j], abs=2 / 65535)
            path = client.path("cam", [(0.0, 0.0), (4.5, 0.0)])
            assert path.unknown_cells > 0 and path.cells and path.lowest_t is not None
            assert path.cells[path.lowest_t].mean == min(c.mean for c in path.cells)
            assert all(c.match is not None for c in path.cells)  # fused cells carry the grid's match layer
            with pytest.raises(Exception, match="unknown: never observed"):
                client.cell("cam", -2.0, 0.0)
            with pytest.raises(Exception, match="outside the grid"):
                client.cell("cam", 50.0, 0.0)
            # The OccupancyGrid CDR decodes with the CDR library and matches the msgpack grid.
            message = ros.typestore().deserialize_cdr(occupancy[-1], "nav_msgs/msg/OccupancyGrid")
            data = np.asarray(message.data, np.int8).reshape(message.info.height, message.info.width)
            assert message.header.frame_id == "odom" and message.info.resolution == pytest.approx(0.25)
            assert message.info.origin.position.x == pytest.approx(header.origin[0])
            assert ((data == -1) == (grid.count == 0)).all()
            known = grid.count > 0
            expected = np.round((1 - grid.traversability[known]) * 100)
            assert np.abs(data[known] - expected).max() <= 1
            # The planner's layers: in the message, the GridMap and the Nav2 costmap alike.
            assert wait_until(lambda: len(grid_maps) >= 3 and len(costmaps) >= 3, 30)
            assert grid.cvar is not None and grid.p_below is not None and grid.age is not None
            assert (grid.cvar[known] <= grid.traversability[known] + 2 / 65535).all()
            assert header.alpha == 0.1 and header.tau == 0.3 and header.expired_cells == 0
            _, layers = decode_grid_map(grid_maps[-1])
            assert (np.isfinite(layers["traversability"]) == known).all()
            np.testing.assert_allclose(layers["cvar"][known], grid.cvar[known], atol=1 / 65535)
            costmap = ros.typestore().deserialize_cdr(costmaps[-1], "nav_msgs/msg/OccupancyGrid")
            costs = np.asarray(costmap.data, np.int8).reshape(data.shape)
            assert ((costs == -1) == ~known).all() and ((costs >= 1) & (costs <= 100))[known].all()
            # A new anchor set resets the grid, and the grid says so.
            client.set_anchors(
                {"anchors": [{"concept": "lake", "position": 0.0}, {"concept": "road", "position": 1.0}]}
            )
            # Swapped to 2 anchors with no frame fused since: a cell answers over the set it was fused with.
            unswapped = client.cell("cam", 2.7, 0.0)
            assert len(unswapped.weights) == 13 and unswapped.anchor_set_version == header.anchor_set_version
            assert [a.concept for a in unswapped.anchors] == default_anchor_set().concepts
            # The robot stood still since: its pose at the frame's capture is known (frames fuse at it).
            put_pose(Pose2D(stamp=104.0, x=1.0, y=0.0, yaw=0.0))
            client.publish_image("cam", textured_image(60, 80, seed=9), stamp=104.0)
            assert wait_until(lambda: grids[-1].header.resets == 1, 60)
            assert "anchor set changed" in grids[-1].header.last_reset
            assert len(client.cell("cam", 2.7, 0.0).weights) == 2
            # A frame taken long after the last pose finds none: not fused, and the status says why.
            changed = np.full((60, 80, 3), 220, np.uint8)  # a new view (an unchanged one is reused, never fused)
            client.publish_image("cam", changed, stamp=110.0)
            assert wait_until(lambda: client.status().grids[0].not_fused_by_reason == {"pose_too_old": 1}, 60)
            status = client.status()
            grid_status = status.grids[0]
            assert grid_status.source == "cam" and grid_status.fused == 4 and grid_status.frame_id == "odom"
            assert grid_status.newest_fused_stamp == 104.0 and grid_status.cameras["cam"].not_fused == "pose_too_old"
            assert grid_status.cameras["cam"].intrinsics == "settings" and grid_status.costmap_ago_s is not None
            assert "cam (" in status_table([status]) and "pose_too_old 1" in status_table([status])
        finally:
            for subscription in subscriptions:
                subscription.undeclare()
            client.close()


def test_pose_camera_info_and_depth_messages() -> None:
    pytest.importorskip("rosbags")
    from gcdtrav.schemas.messages import MessageError, Pose2D
    from gcdtrav.service.ros import cdr as ros
    from gcdtrav.service.ros.cdr import decode_camera_info_frame, decode_depth, decode_pose

    types = ros.typestore().types
    header = ros.make_header(12.5, "odom")
    yaw = 0.7
    pose = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=3.0, y=-1.0, z=0.0),
        orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)),
    )
    twist = types["geometry_msgs/msg/Twist"](
        linear=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
        angular=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
    )
    odometry = types["nav_msgs/msg/Odometry"](
        header=header,
        child_frame_id="base_link",
        pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
    )
    decoded = decode_pose(bytes(ros.typestore().serialize_cdr(odometry, "nav_msgs/msg/Odometry")), "odometry")
    assert (decoded.x, decoded.y, decoded.frame_id, decoded.stamp) == (3.0, -1.0, "odom", 12.5)
    assert decoded.yaw == pytest.approx(yaw)
    assert decode_pose(Pose2D(stamp=1.0, x=1.0, y=2.0, yaw=0.1).pack(), "gcdtrav").y == 2.0
    with pytest.raises(MessageError):
        decode_pose(b"\x00\x01\x00\x00junk", "odometry")

    info_type = types["sensor_msgs/msg/CameraInfo"]
    roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    info = info_type(
        header=header,
        height=480,
        width=640,
        distortion_model="plumb_bob",
        d=np.zeros(5),
        k=np.array([500.0, 0, 320, 0, 510.0, 240, 0, 0, 1]),
        r=np.eye(3).ravel(),
        p=np.zeros(12),
        binning_x=0,
        binning_y=0,
        roi=roi,
    )
    camera, _ = decode_camera_info_frame(bytes(ros.typestore().serialize_cdr(info, "sensor_msgs/msg/CameraInfo")))
    assert (camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height) == (500, 510, 320, 240, 640, 480)

    millimetres = np.array([[1000, 2500], [0, 65535]], np.uint16)
    image = types[ros.IMAGE](
        header=header,
        height=2,
        width=2,
        encoding="16UC1",
        is_bigendian=0,
        step=4,
        data=millimetres.view(np.uint8).ravel(),
    )
    depth = decode_depth(bytes(ros.typestore().serialize_cdr(image, ros.IMAGE)))
    np.testing.assert_allclose(depth, millimetres * 1e-3, rtol=1e-6)
