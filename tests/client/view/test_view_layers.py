"""The grid layers' channels as the viewer draws them, the Nav2 costmap read from its CDR without ROS, and where
the robot and its camera are (transforms, calibration, frustum), checked against the service's own code."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("foxglove", reason="the view extra: pip install 'gcdtrav[view]'")
pytest.importorskip("google.protobuf")

from gcdtrav.client.client import Grid
from gcdtrav.client.view import frames, grid_layers, pictures, probe
from gcdtrav.schemas.messages import GridHeader
from gcdtrav.schemas.settings import CameraIntrinsics, CameraMountSettings
from protobuf_decode import decode_foxglove
from view_fakes import grid_payload

HEADER = GridHeader(
    source="cam", seq=0, stamp=5.0, frame_id="odom", origin=(-1.0, -1.0), resolution=0.5, cells=4,
    anchor_set_version="x", resets=0, known_cells=15, instance="i", robot=(0.25, -0.75, 0.0), alpha=0.1, tau=0.3,
)  # fmt: skip
INTRINSICS = CameraIntrinsics(fx=100, fy=100, cx=80, cy=60, width=160, height=120)


def test_every_planner_layer_has_its_values_and_colours_unknown_cells_transparent() -> None:
    grid = Grid.from_payload(grid_payload("cam", layers=True))
    layers = grid_layers.layer_values(grid)
    assert list(layers) == ["traversability", "uncertainty", "cvar", "p_below", "match", "age", "speed"]
    kind, cvar = layers["cvar"]
    cells = np.frombuffer(grid_layers.layer_cells(cvar, kind), np.dtype([("v", "<f4"), ("rgba", "u1", (4,))]))
    cells = cells.reshape(4, 4)
    assert np.isnan(cells["v"][0, 0]) and cells["rgba"][0, 0, 3] == 0  # unknown: NaN, transparent
    assert np.allclose(cells["v"][1:, 1:], 0.25, atol=1e-4) and (cells["rgba"][1:, 1:, 3] == 255).all()
    expected = pictures.colorize_traversability(np.array([0.25], np.float32))[0]
    assert (cells["rgba"][1, 1, :3] == expected).all()  # CVaR reads like T
    assert np.allclose(layers["age"][1][1:, 1:], 1.5) and np.isnan(layers["age"][1][0, 0])
    assert np.allclose(layers["speed"][1], 0.6, atol=1e-4)  # every cell has a speed, the unknown one too
    old = Grid.from_payload(grid_payload("cam"))  # a 1.1 writer: no risk layers, no channels for them
    assert list(grid_layers.layer_values(old)) == ["traversability", "uncertainty"]


def test_scales_run_the_right_way() -> None:
    def colour(kind: pictures.MapKind, value: float) -> np.ndarray:
        return pictures.colour_map(np.array([[value]], np.float32), kind)[0, 0].astype(int)

    red, green = 0, 1
    assert colour("p_below", 0.9)[red] > colour("p_below", 0.9)[green]  # likely below tau: red
    assert colour("p_below", 0.0)[green] > colour("p_below", 0.0)[red]
    assert colour("cost", 98)[red] > colour("cost", 98)[green] and colour("cost", 1)[green] > colour("cost", 1)[red]
    assert tuple(colour("cost", 100)) == pictures.LETHAL_COLOUR
    assert colour("match", 1.0).sum() > colour("match", 0.0).sum()  # well described is bright
    assert tuple(colour("T", float("nan"))) == pictures.UNKNOWN_COLOUR


def test_layer_pictures_have_y_up_the_robot_and_a_titled_legend() -> None:
    values = np.full((4, 4), np.nan, np.float32)
    values[0, :] = 0.0  # row 0 is the lowest y: it is drawn at the bottom
    values[3, :] = 1.0
    picture = grid_layers.layer_picture(values, "cvar", HEADER)
    side = picture.shape[0]
    assert side >= pictures.MIN_HEIGHT and picture.shape[1] == side + pictures.LEGEND_WIDTH
    top, bottom = picture[2, 2].astype(int), picture[side - 3, 2].astype(int)
    assert top[1] > top[0] and bottom[0] > bottom[1]  # green (T 1) at the top, red (T 0) at the bottom
    # the robot at (0.25, -0.75): column 2.5, row 0.5 from the bottom -> a white dot there
    robot = picture[round(side - 0.5 * side / 4), round(2.5 * side / 4)]
    assert tuple(robot) == grid_layers.ROBOT_COLOUR
    assert grid_layers.layer_title("cvar", HEADER) == "CVaR 0.10"
    assert grid_layers.layer_title("p_below", HEADER) == "P(T<0.30)"


def test_the_costmap_is_read_from_the_services_own_cdr() -> None:
    pytest.importorskip("rosbags")
    from gcdtrav.service.ros.cdr import occupancy_values_cdr

    data = np.array([[-1, 1, 50, 98], [100, 100, 3, -1], [7, 7, 7, 7], [0, 1, 2, 3]], np.int8)
    costmap = grid_layers.decode_occupancy_grid(occupancy_values_cdr(HEADER, data))
    assert costmap.frame_id == "odom" and costmap.origin == (-1.0, -1.0) and costmap.resolution == 0.5
    assert costmap.stamp == pytest.approx(5.0) and np.array_equal(costmap.data, data)
    values = costmap.values()
    assert np.isnan(values[0, 0]) and values[1, 0] == 100 and values[0, 3] == 98
    with pytest.raises(ValueError, match="OccupancyGrid"):
        grid_layers.decode_occupancy_grid(b"\x00\x00\x00\x00rest")
    with pytest.raises((ValueError, Exception)):
        grid_layers.decode_occupancy_grid(occupancy_values_cdr(HEADER, data)[:-5])  # truncated


def rotate(q: dict[str, float], vector: np.ndarray) -> np.ndarray:
    x, y, z, w = (q[name] for name in "xyzw")
    u = np.array([x, y, z])
    return 2 * np.dot(u, vector) * u + (w * w - np.dot(u, u)) * vector + 2 * w * np.cross(u, vector)


@pytest.mark.parametrize("mount", [CameraMountSettings(z=1.2, pitch=0.35, yaw=0.5),
                                   CameraMountSettings(x=0.3, y=-0.1, z=0.8, roll=0.2, pitch=-0.4, yaw=-2.9),
                                   CameraMountSettings(yaw=math.pi)])  # fmt: skip
def test_the_mount_transform_is_the_services_projection(mount: CameraMountSettings) -> None:
    from gcdtrav.service.grid.geometry import CameraMount

    service = CameraMount(**mount.model_dump())
    transform = decode_foxglove(frames.mount_transform(frames.Timestamp(sec=0, nsec=0), mount, "front"))
    assert (transform["parent_frame_id"], transform["child_frame_id"]) == ("base_link", "front")
    for axis in np.eye(3):  # each optical axis lands where the service's geometry puts it
        assert np.allclose(rotate(transform["rotation"], axis), service.rotation_optical @ axis, atol=1e-9)
    t = transform["translation"]
    assert (t["x"], t["y"], t["z"]) == (mount.x, mount.y, mount.z)


def test_the_robot_transform_and_frustum() -> None:
    transform = decode_foxglove(
        frames.robot_transform(frames.Timestamp(sec=1, nsec=0), "odom", (2.0, 1.0, math.pi / 2))
    )
    assert (transform["parent_frame_id"], transform["child_frame_id"]) == ("odom", "base_link")
    assert transform["translation"] == {"x": 2.0, "y": 1.0, "z": 0.0}
    assert np.allclose(rotate(transform["rotation"], np.array([1.0, 0, 0])), [0, 1, 0])  # facing +y
    corners = frames.frustum_corners(INTRINSICS, depth=2.0)
    pixels = [(x / z * INTRINSICS.fx + INTRINSICS.cx, y / z * INTRINSICS.fy + INTRINSICS.cy) for x, y, z in corners]
    assert np.allclose(pixels, [(0, 0), (160, 0), (160, 120), (0, 120)])  # back through K: the image's corners
    entity = decode_foxglove(frames.frustum_entity(frames.Timestamp(sec=1, nsec=0), "cam", INTRINSICS, "front"))
    assert entity["frame_id"] == "front" and len(entity["lines"][0]["points"]) == 16
    apex_to_corner = entity["lines"][0]["points"][1]
    assert (apex_to_corner["x"], apex_to_corner["y"], apex_to_corner["z"]) == pytest.approx(corners[0])


def test_calibration_follows_the_image_size() -> None:
    calibration = decode_foxglove(frames.calibration(frames.Timestamp(sec=0, nsec=0), INTRINSICS, "front", (320, 240)))
    assert (calibration["width"], calibration["height"], calibration["frame_id"]) == (320, 240, "front")
    assert calibration["K"] == [200.0, 0.0, 160.0, 0.0, 200.0, 120.0, 0.0, 0.0, 1.0]
    assert decode_foxglove(frames.calibration(frames.Timestamp(sec=0, nsec=0), INTRINSICS, "f", None))["width"] == 160
    assert frames.camera_frame("r1/front", "") == "r1/front/camera" and frames.camera_frame("x", "cam0") == "cam0"


def test_cameras_come_from_the_services_settings_file(tmp_path: Path) -> None:
    settings = tmp_path / "gcdtrav.yaml"
    settings.write_text(
        "grids:\n"
        "  - source: r1/all\n"
        "    cameras:\n"
        "      - {source: r1/left, intrinsics: {fx: 500, fy: 500, cx: 320, cy: 240, width: 640, height: 480},\n"
        "         mount: {z: 1.2, pitch: 0.35, yaw: 0.5}}\n"
        "      - {source: r1/right, camera_info_key: r1/right/camera_info, mount: {z: 1.2, yaw: -0.5}}\n"
    )
    cameras = frames.cameras_from_settings(settings)
    assert set(cameras) == {"r1/left", "r1/right"}
    assert cameras["r1/left"].mount.yaw == 0.5 and cameras["r1/left"].intrinsics is not None
    assert cameras["r1/right"].intrinsics is None  # its intrinsics stay on the robot: no frustum


def test_probe_parameters_and_published_points() -> None:
    target = probe.apply_probe_parameters(probe.ProbeTarget(), {"probe/source": "cam", "probe/x": 3, "probe/y": 2.5})
    assert target == probe.ProbeTarget("cam", "patch", 3.0, 2.5) and target.active
    for bad in ({"probe/target": "pixel"}, {"probe/x": "left"}, {"probe/x": float("nan")}, {"probe/z": 1}):
        with pytest.raises(ValueError, match=str(next(iter(bad)))):
            probe.apply_probe_parameters(target, bad)
    point = probe.clicked_point(b'{"header": {"frame_id": "base_link"}, "point": {"x": 1.0, "y": 0.0, "z": 0}}')
    assert probe.to_grid_frame(point, "odom", (2.0, 1.0, math.pi / 2), "base_link") == pytest.approx((2.0, 2.0))
    assert probe.to_grid_frame(point, "odom", None, "base_link") is None  # no pose: cannot place it
    assert probe.to_grid_frame(probe.ClickedPoint("odom", 1, 2), "odom", None, "base_link") == (1, 2)
    with pytest.raises(ValueError, match="not a point"):
        probe.clicked_point(b'{"point": {"x": "east"}}')
