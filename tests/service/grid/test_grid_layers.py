"""A grid's planner layers, zenoh-free: risk measures per cell, fused match, age and expiry, the Nav2 costmap,
several cameras in one grid, and the settings' two forms."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from gcdtrav.schemas.anchors import Anchor, AnchorSet, default_anchor_set
from gcdtrav.schemas.settings import GridSettings, RiskSettings, ServiceSettings
from gcdtrav.service.grid.fusion import GridSpec, GroundGrid
from gcdtrav.service.grid.layers import (
    HIGHEST_COST,
    LETHAL_COST,
    LOWEST_COST,
    UNKNOWN_COST,
    GridLayers,
    grid_layers,
    nav2_costs,
)
from gcdtrav.service.runtime.grids import GridOutputs
from gcdtrav.service.runtime.history import FrameRecord
from pydantic import ValidationError

from tools.loopback import grid_update

# water 0.0 and road 1.0, point masses (the paper's kind), and a mid Gaussian
THREE = AnchorSet(
    anchors=[
        Anchor(concept="water", position=0.0),
        Anchor(concept="gravel", position=0.5, width=0.1),
        Anchor(concept="road", position=1.0),
    ]
)
POSITIONS, WIDTHS = np.array(THREE.positions), np.array(THREE.widths)
INTRINSICS = {"fx": 60, "fy": 60, "cx": 40, "cy": 30, "width": 80, "height": 60}


def small_grid(max_age_s: float | None = None) -> GroundGrid:
    spec = GridSpec(size_m=2.0, resolution_m=0.5, half_life_s=100.0, max_age_s=max_age_s)
    return GroundGrid(spec, anchor_count=3, origin=(0.0, 0.0))


def cell_point(i: int, j: int) -> list[float]:
    """A point inside cell (i, j) of ``small_grid``."""
    return [0.5 * j + 0.2, 0.5 * i + 0.3]


def test_layers_are_the_risk_measures_of_each_known_cell() -> None:
    grid = small_grid()
    rng = np.random.default_rng(3)
    cells = [(0, 0), (0, 3), (2, 1), (3, 3)]
    points = np.array([cell_point(i, j) for i, j in cells for _ in range(5)])
    weights = rng.dirichlet(np.ones(3), size=len(points)).T
    grid.add(points, weights, stamp=1.0, anchors=THREE, match=np.full(len(points), 0.7))
    layers = grid_layers(grid, POSITIONS, WIDTHS, alpha=0.2, tau=0.3)
    known = layers.known
    assert known.sum() == len(cells) and (layers.count[known] == 5).all()
    assert (layers.cvar[known] <= layers.traversability[known] + 1e-6).all()  # CVaR <= mean
    assert ((layers.p_below[known] >= 0) & (layers.p_below[known] <= 1)).all()
    for values in (layers.traversability, layers.cvar, layers.p_below, layers.match):
        assert np.isnan(values[~known]).all()
    # a cell with all its weight on water: CVaR 0 and P(T < 0.3) = 1; all on road: CVaR 1, P = 0
    grid.add(np.array([cell_point(1, 0), cell_point(1, 1)]), np.array([[1.0, 0.0], [0.0, 0.0], [0.0, 1.0]]), 1.0, THREE)
    layers = grid_layers(grid, POSITIONS, WIDTHS, alpha=0.2, tau=0.3)
    assert (layers.cvar[1, 0], layers.p_below[1, 0]) == (0.0, 1.0)
    assert (layers.cvar[1, 1], layers.p_below[1, 1]) == (pytest.approx(1.0), 0.0)
    assert layers.alpha == 0.2 and layers.tau == 0.3 and layers.lethal_tau == 0.3
    # the costmap's threshold apart from tau: P(T < 0.6) of a cell half gravel is about a half
    grid.add(np.array([cell_point(1, 2)]), np.array([[0.0], [1.0], [0.0]]), 1.0, THREE)
    layers = grid_layers(grid, POSITIONS, WIDTHS, alpha=0.2, tau=0.3, lethal_tau=0.5)
    assert layers.p_lethal[1, 2] == pytest.approx(0.5, abs=1e-6) and layers.p_below[1, 2] < 0.03


def test_match_scores_are_fused_like_the_weights() -> None:
    grid = GroundGrid(GridSpec(size_m=1.0, resolution_m=0.5, half_life_s=1.0), anchor_count=3, origin=(0.0, 0.0))
    one_hot = np.array([[1.0, 1.0], [0.0, 0.0], [0.0, 0.0]])
    grid.add(np.array([[0.1, 0.1], [0.2, 0.2]]), one_hot, stamp=0.0, anchors=THREE, match=np.array([0.2, 0.8]))
    assert grid.match()[0, 0] == pytest.approx(0.5)
    # one half-life later a pixel of 1.0: (0.5 * (0.2 + 0.8) + 1.0) / (0.5 * 2 + 1) = 0.75
    grid.add(np.array([[0.3, 0.3]]), one_hot[:, :1], stamp=1.0, anchors=THREE, match=np.array([1.0]))
    assert grid.match()[0, 0] == pytest.approx(0.75)
    assert np.isnan(grid.match()[1, 1])
    grid.add(np.array([[0.7, 0.7]]), one_hot[:, :1], stamp=1.0, anchors=THREE)  # no scores: matched
    assert grid.match()[1, 1] == 1.0


def test_age_grows_with_later_frames_and_scrolls_with_the_cells() -> None:
    grid = small_grid()
    one = np.array([[1.0], [0.0], [0.0]])
    grid.add(np.array([cell_point(0, 0)]), one, stamp=10.0, anchors=THREE)
    assert grid.age()[0, 0] == 0.0 and np.isnan(grid.age()[3, 3])
    grid.add(np.array([cell_point(3, 3)]), one, stamp=12.5, anchors=THREE)
    grid.add(np.array([cell_point(3, 3)]), one, stamp=14.0, anchors=THREE)
    assert grid.age()[0, 0] == 4.0 and grid.age()[3, 3] == 0.0
    grid.add(np.array([cell_point(3, 3)]), one, stamp=13.0, anchors=THREE)  # an older frame of another camera
    assert grid.age()[3, 3] == 0.0 and grid.stamp == 14.0
    grid.scroll_to((0.5, 0.5))  # one cell along +x and +y: the old (3, 3) is now (2, 2), (0, 0) left
    assert grid.age()[2, 2] == 0.0 and np.isnan(grid.age()[3, 3]) and np.isnan(grid.age()).sum() == 15


@pytest.mark.parametrize("never", [None, 0.0])
def test_cells_never_expire_without_a_max_age(never: float | None) -> None:
    grid = small_grid(max_age_s=never)
    one = np.array([[1.0], [0.0], [0.0]])
    grid.add(np.array([cell_point(0, 0)]), one, stamp=0.0, anchors=THREE)
    grid.add(np.array([cell_point(3, 3)]), one, stamp=1e6, anchors=THREE)
    assert grid.known[0, 0] and not grid.expired.any() and grid.age()[0, 0] == 1e6


def test_cells_expire_after_max_age_and_come_back_when_seen() -> None:
    grid = small_grid(max_age_s=2.0)
    one = np.array([[1.0], [0.0], [0.0]])
    grid.add(np.array([cell_point(0, 0), cell_point(1, 1)]), np.hstack([one, one]), stamp=0.0, anchors=THREE)
    grid.add(np.array([cell_point(1, 1)]), one, stamp=1.5, anchors=THREE)
    grid.add(np.array([cell_point(3, 3)]), one, stamp=2.0, anchors=THREE)  # exactly max_age_s: still known
    assert grid.known[0, 0] and not grid.expired.any()
    grid.add(np.array([cell_point(3, 3)]), one, stamp=2.01, anchors=THREE)
    assert not grid.known[0, 0] and grid.expired[0, 0] and grid.expired.sum() == 1
    assert grid.cell_weights(0, 0) is None and grid.age()[0, 0] == pytest.approx(2.01)  # keeps its age
    layers = grid_layers(grid, POSITIONS, WIDTHS, 0.1, 0.3)
    assert np.isnan(layers.traversability[0, 0]) and layers.count[0, 0] == 0
    grid.add(np.array([cell_point(0, 0)]), np.array([[0.0], [0.0], [1.0]]), stamp=3.0, anchors=THREE)
    assert grid.known[0, 0] and not grid.expired[0, 0] and grid.count[0, 0] == 1
    assert grid.cell_weights(0, 0).tolist() == [0.0, 0.0, 1.0]  # nothing of before the expiry


def test_a_tiny_max_age_expires_everything_but_the_newest_frame() -> None:
    grid = small_grid(max_age_s=1e-9)
    rng = np.random.default_rng(0)
    points = rng.uniform(0, 2, size=(200, 2))
    grid.add(points, rng.dirichlet(np.ones(3), 200).T, stamp=5.0, anchors=THREE)
    known = int(grid.known.sum())
    grid.add(np.array([[1.9, 1.9]]), np.array([[1.0], [0.0], [0.0]]), stamp=5.001, anchors=THREE)
    assert grid.known.sum() == 1 and grid.expired.sum() == known - 1  # cell (3, 3) seen again


# ---- the Nav2 costmap -----------------------------------------------------------------------------------


def layers_of(cvar: list[float], p_lethal: list[float], match: list[float], count: list[int]) -> GridLayers:
    def row(values: list[float]) -> np.ndarray:
        return np.array([values], np.float32)

    known = np.array([count]) > 0
    cvar_row = np.where(known, row(cvar), np.nan).astype(np.float32)
    return GridLayers(
        traversability=cvar_row,
        uncertainty=cvar_row,
        cvar=cvar_row,
        p_below=row(p_lethal),
        match=row(match),
        count=np.array([count]),
        age=np.zeros((1, len(count))),
        p_lethal=row(p_lethal),
        alpha=0.1,
        tau=0.1,
        lethal_tau=0.1,
    )


def test_nav2_costs_at_the_edges_of_the_table() -> None:
    layers = layers_of(
        cvar=[0.0, 1.0, 0.5, 0.9, 0.9, 0.9, 0.9, 0.2, -0.01, 1.01],
        p_lethal=[0.0, 0.0, 0.0, 0.26, 0.25, 0.0, 0.0, 0.9, 0.0, 0.0],
        match=[1.0, 1.0, 1.0, 1.0, 1.0, 0.39, 0.4, 0.1, 1.0, 1.0],
        count=[1, 1, 1, 1, 1, 1, 1, 0, 1, 1],
    )
    costs = nav2_costs(layers, lethal_probability=0.25, min_match=0.4)
    assert costs.dtype == np.int8
    expected = [
        HIGHEST_COST,  # CVaR 0: the worst graded cost, 98
        LOWEST_COST,  # CVaR 1: 1, never 0 (free)
        1 + round(97 * 0.5),  # 49 (round half to even)
        LETHAL_COST,  # P(T < lethal_tau) over lethal_probability
        1 + round(97 * 0.1),  # at lethal_probability exactly: graded
        UNKNOWN_COST,  # match below min_match: nothing in the anchor set describes it
        1 + round(97 * 0.1),  # match at min_match: known
        UNKNOWN_COST,  # never observed (or expired), whatever else
        HIGHEST_COST,  # a CVaR a hair below 0 (a Gaussian anchor's tail) is clipped
        LOWEST_COST,
    ]
    assert costs[0].tolist() == expected
    assert (HIGHEST_COST, LOWEST_COST, LETHAL_COST, UNKNOWN_COST) == (98, 1, 100, -1)
    # what Nav2's static layer makes of them (static_layer.cpp interpretValue, trinary_costmap false):
    # value / lethal_cost_threshold * LETHAL_OBSTACLE (254), truncated; 100 lethal; -1 (255) unknown
    nav2 = [int(v / 100 * 254) for v in (LOWEST_COST, HIGHEST_COST)]
    assert nav2 == [2, 248] and nav2[1] < 253  # below INSCRIBED_INFLATED_OBSTACLE: graded, never an obstacle


def test_min_match_zero_never_hides_a_cell() -> None:
    layers = layers_of(cvar=[0.5, 0.5], p_lethal=[0.0, 0.0], match=[0.0, 1e-9], count=[3, 3])
    assert (nav2_costs(layers, 0.25, min_match=0.0) == 1 + round(97 * 0.5)).all()
    assert (nav2_costs(layers, 1.0, min_match=1.0) == UNKNOWN_COST).all()
    assert (nav2_costs(layers_of([0.5], [1.0], [1.0], [3]), 0.0, 0.0) == LETHAL_COST).all()  # any chance: lethal


# ---- settings ------------------------------------------------------------------------------------------


def test_the_single_camera_form_still_validates_unchanged() -> None:
    config = GridSettings.model_validate({"source": "cam", "intrinsics": INTRINSICS, "mount": {"z": 1.2}})
    (camera,) = config.camera_list()
    assert (camera.source, camera.mount.z, camera.intrinsics) == ("cam", 1.2, config.intrinsics)
    assert config.cameras is None and config.max_age_s == 30.0 and not config.grid_map and not config.costmap
    assert GridSettings.model_validate(config.model_dump()) == config


def two_cameras(**overrides: Any) -> dict[str, Any]:
    return {
        "cameras": [
            {"source": "left", "intrinsics": INTRINSICS, "mount": {"z": 1.0, "yaw": 0.3}},
            {"source": "right", "camera_info_key": "r/info", "mount": {"z": 1.0, "yaw": -0.3}},
        ],
        "size_m": 8.0,
        "resolution_m": 0.25,
    } | overrides


def test_the_cameras_form_is_published_under_the_first_camera_or_its_source() -> None:
    config = GridSettings.model_validate(two_cameras())
    assert config.source == "left" and [c.source for c in config.camera_list()] == ["left", "right"]
    assert GridSettings.model_validate(config.model_dump()) == config  # round trip
    assert GridSettings.model_validate(two_cameras(source="both")).source == "both"


@pytest.mark.parametrize(
    ("grid", "message"),
    [
        (two_cameras(intrinsics=INTRINSICS), "either cameras or the single-camera fields, not both"),
        (two_cameras(mount={"z": 2.0}), "move mount into each camera"),
        ({"size_m": 4.0}, "needs a source \\(one camera\\) or cameras"),
        ({"source": "cam"}, "give intrinsics or a camera_info_key"),
        ({"cameras": []}, "at least 1 item"),
        ({"cameras": [{"source": "a"}]}, "camera 'a': give intrinsics or a camera_info_key"),
        ({"cameras": [{"source": "a", "intrinsics": INTRINSICS}] * 2}, "a camera is listed twice"),
    ],
)
def test_a_grid_gives_one_form_or_the_other(grid: dict[str, Any], message: str) -> None:
    with pytest.raises(ValidationError, match=message):
        GridSettings.model_validate(grid)


def test_a_camera_feeds_one_grid_and_a_source_names_one_grid() -> None:
    single = {"source": "left", "intrinsics": INTRINSICS}
    with pytest.raises(ValidationError, match="a camera feeds two grids"):
        ServiceSettings.model_validate({"grids": [two_cameras(source="both"), single]})
    with pytest.raises(ValidationError, match="two grids are published under the same source"):
        ServiceSettings.model_validate({"grids": [two_cameras(), single | {"source": "x"}, single | {"source": "x"}]})


# ---- several cameras, one grid -------------------------------------------------------------------------

MAP_H, MAP_W = 48, 64
ANCHORS = default_anchor_set()


def frame(stamp: float, weights: np.ndarray) -> FrameRecord:
    return FrameRecord(0, stamp, "", weights.astype(np.float16), ANCHORS, (80, 60))


def weights_on(anchor: int) -> np.ndarray:
    weights = np.zeros((len(ANCHORS), MAP_H, MAP_W), np.float32)
    weights[anchor] = 1.0
    return weights


def info_cdr() -> bytes:
    from gcdtrav.service.ros import cdr as ros

    types = ros.typestore().types
    roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    info = types["sensor_msgs/msg/CameraInfo"](
        header=ros.make_header(1.0, "right"), height=60, width=80, distortion_model="plumb_bob", d=np.zeros(5),
        k=np.array([60.0, 0, 40, 0, 60.0, 30, 0, 0, 1]), r=np.eye(3).ravel(), p=np.zeros(12),
        binning_x=0, binning_y=0, roi=roi,
    )  # fmt: skip
    return bytes(ros.typestore().serialize_cdr(info, "sensor_msgs/msg/CameraInfo"))


def counts(config: dict[str, Any], frames: list[tuple[str, float, np.ndarray]]) -> tuple[np.ndarray, GridOutputs]:
    grids = GridOutputs([GridSettings.model_validate(config)], len(ANCHORS), "test")
    for camera in grids.camera_grids:
        grids.set_camera_info(camera, info_cdr())
    update = None
    for source, stamp, weights in frames:
        update = grid_update(grids, source, frame(stamp, weights), weights) or update
    assert update is not None
    from gcdtrav.client.client import Grid

    return Grid.from_payload(update.message.pack()).count, grids


def test_two_overlapping_cameras_fuse_into_one_grid() -> None:
    water, road = ANCHORS.concepts.index("water"), ANCHORS.concepts.index("asphalt")
    left = ("left", 1.0, weights_on(water))
    right = ("right", 1.0, weights_on(road))
    both, grids = counts(two_cameras(), [left, right])
    only_left, _ = counts(two_cameras(), [left])
    only_right, _ = counts(two_cameras(), [right])
    np.testing.assert_array_equal(both, only_left + only_right)  # every cell counts the pixels of both
    overlap = (only_left > 0) & (only_right > 0)
    assert overlap.any() and ((only_left > 0) & ~overlap).any() and ((only_right > 0) & ~overlap).any()
    grid = grids.sources["left"].grid
    rows, cols = np.nonzero(overlap)
    # Each camera alone covers only its side. Level cameras: a pixel's ground bearing is yaw - atan(u'), so the
    # left one (yaw +0.3, patch centres up to atan(37.5 / 60) = 0.56 off axis) sees bearings -0.26 to 0.86,
    # the right one -0.86 to 0.26 (cell centres within 0.1 of that beyond 1.5 m).
    i, j = np.indices(both.shape)
    r = grid.spec.resolution_m
    x, y = grid.origin[0] + (j + 0.5) * r, grid.origin[1] + (i + 0.5) * r
    bearing, far = np.arctan2(y, x), np.hypot(x, y) > 1.5
    assert (only_right[far & (bearing > 0.36)] == 0).all() and (only_left[far & (bearing > 0.36)] > 0).any()
    assert (only_left[far & (bearing < -0.36)] == 0).all() and (only_right[far & (bearing < -0.36)] > 0).any()
    assert (np.abs(bearing[overlap & far]) < 0.36).all()
    # in the overlap the two concepts are mixed by pixel count
    i, j = rows[0], cols[0]
    weights = grid.cell_weights(i, j)
    assert weights is not None
    assert weights[water] == pytest.approx(only_left[i, j] / both[i, j], abs=1e-3)
    assert weights[road] == pytest.approx(only_right[i, j] / both[i, j], abs=1e-3)


def test_a_grid_of_several_cameras_publishes_under_its_name_and_waits_for_each_camera() -> None:
    grids = GridOutputs([GridSettings.model_validate(two_cameras(source="both"))], len(ANCHORS), "test")
    assert grid_update(grids, "both", frame(1.0, weights_on(0)), weights_on(0)) is None  # not a camera
    assert grid_update(grids, "right", frame(1.0, weights_on(0)), weights_on(0)) is None  # no CameraInfo yet
    update = grid_update(grids, "left", frame(1.0, weights_on(0)), weights_on(0))
    assert update is not None and update.source == "both" and update.message.header.source == "both"
    inputs = {(key, source, reason) for key, source, _, reason in grids.inputs()}
    assert inputs == {("r/info", "right", "bad_camera_info")}


def test_grid_outputs_say_their_levels_age_and_expired_cells() -> None:
    config = two_cameras(max_age_s=0.5, occupancy_grid=True, grid_map=True, costmap=True)
    now = [100.0]
    grids = GridOutputs(
        [GridSettings.model_validate(config)], len(ANCHORS), "t", RiskSettings(alpha=0.3, tau=0.2), lambda: now[0]
    )
    grids.set_camera_info("right", info_cdr())
    first = grid_update(grids, "left", frame(10.0, weights_on(0)), weights_on(0), match=np.full((MAP_H, MAP_W), 0.25))
    assert first is not None
    header = first.message.header
    assert (header.alpha, header.tau, header.expired_cells, header.age_s) == (0.3, 0.2, 0, 90.0)
    assert None not in (first.occupancy, first.uncertainty, first.grid_map, first.costmap)
    later = grid_update(grids, "right", frame(11.0, weights_on(0)), weights_on(0))
    assert later is not None
    from gcdtrav.client.client import Grid

    grid = Grid.from_payload(later.message.pack())
    assert grid.header.expired_cells > 0 and grid.header.age_s == 89.0 and grid.header.seq == 1
    assert grid.cvar is not None and grid.p_below is not None and grid.match is not None and grid.age is not None
    known = grid.count > 0
    assert np.nanmax(grid.age[known]) == 0.0  # only the right camera's cells are left
    expired_age = grid.age[~known & ~np.isnan(grid.age)]
    assert expired_age.size == grid.header.expired_cells and (expired_age == 1.0).all()
    assert (grid.match[known] == 1.0).all()  # no scores: matched; the left camera's 0.25 expired
    assert set(grid.planning_layers()) == {"traversability", "cvar", "p_below"}
    assert math.isnan(grid.cvar[~known][0])


def test_the_nav2_example_subscribes_the_topic_the_service_publishes() -> None:
    from pathlib import Path

    import yaml
    from gcdtrav.schemas.settings import load_settings
    from gcdtrav.service.ros.cdr import output_topic

    examples = Path(__file__).resolve().parents[3] / "examples" / "nav2"
    settings = load_settings(examples / "gcdtrav.yaml", environ={})
    (grid,) = settings.grids
    assert grid.costmap and grid.grid_map and grid.tf is not None and grid.tf.mount and grid.tf.pose
    costmap = yaml.safe_load((examples / "nav2_costmap.yaml").read_text())["local_costmap"]["local_costmap"]
    parameters = costmap["ros__parameters"]
    assert parameters["global_frame"] == grid.tf.odom_frame  # the grid's frame, the pose's from tf
    topic = output_topic(settings.ros_output.costmap_topic, "/" + grid.source)
    assert parameters["gcdtrav_layer"]["map_topic"] == topic == "/camera/front/image_raw/gcdtrav/grid/costmap"
    assert parameters["gcdtrav_layer"]["map_subscribe_transient_local"] is True
    assert parameters["trinary_costmap"] is False and parameters["track_unknown_space"] is True
    assert parameters["resolution"] == grid.resolution_m
