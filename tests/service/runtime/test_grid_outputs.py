"""The grid's outputs through the OutputBuilder: every CDR message on its key and on the camera's ROS topics;
the outputs only encode the grid the worker fused."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from fakes import processed
from gcdtrav.schemas.experience import OperatorQuestion
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.runtime.grids import GridOutputs
from gcdtrav.service.runtime.outputs import OutputBuilder

pytest.importorskip("rosbags")

from gcdtrav.service.ros import cdr as ros

from tools.ros_fixtures import decode_grid_map

GRID_MAP_HASH = "RIHS01_343b0e72887541beda6b035cc053f2d6fffaad9d6dcb2773c15a808dfca31fde"


def test_the_grids_cdr_outputs_go_on_their_keys_and_the_cameras_ros_topics() -> None:
    grid = {
        "source": "cam",
        "intrinsics": {"fx": 40, "fy": 40, "cx": 32, "cy": 24, "width": 64, "height": 48},
        "mount": {"z": 1.0, "pitch": 0.5},
        "size_m": 6.0,
        "resolution_m": 0.5,
        "occupancy_grid": True,
        "grid_map": True,
        "costmap": True,
    }
    settings = ServiceSettings.model_validate(
        {"grids": [grid], "preview": False, "ros_output": {"enabled": True, "preview": "none"}}
    )
    done = processed("cam")
    camera = ros.RosTopic("/cam/image_raw", ros.IMAGE, "rmw_zenoh", type_hash=ros.type_hash(ros.IMAGE))
    pending = replace(done.inferred.pending, ros=camera)
    done = replace(done, inferred=replace(done.inferred, pending=pending, ros_header=ros.make_header(12.5, "cam")))
    grids = GridOutputs(settings.grids, 13, "test", settings.risk)
    maps = done.result.maps
    done = replace(done, grid=grids.fuse("cam", done.record, maps.weights, maps.match, camera))  # as the worker does
    outputs = {output.key: output for output in OutputBuilder(settings, "fake").build(done)}
    for layer in ("occupancy", "uncertainty", "gridmap", "costmap"):
        assert f"gcdtrav/out/cam/grid/{layer}" in outputs
    gridmap_key = f"0/cam/image_raw/gcdtrav/grid/gridmap/grid_map_msgs::msg::dds_::GridMap_/{GRID_MAP_HASH}"
    costmap_key = (
        f"0/cam/image_raw/gcdtrav/grid/costmap/nav_msgs::msg::dds_::OccupancyGrid_/{ros.type_hash(ros.OCCUPANCY_GRID)}"
    )
    assert outputs[gridmap_key].qos == "grid" and outputs[costmap_key].qos == "grid"
    assert outputs[gridmap_key].payload == outputs["gcdtrav/out/cam/grid/gridmap"].payload
    costmap = ros.typestore().deserialize_cdr(outputs[costmap_key].payload, ros.OCCUPANCY_GRID)
    values = np.asarray(costmap.data, np.int8)
    assert set(np.unique(values)) <= {-1, 100} | set(range(1, 99)) and (values == -1).any() and (values > 0).any()
    _, layers = decode_grid_map(outputs[gridmap_key].payload)
    assert set(layers) == {"traversability", "uncertainty", "cvar", "p_below", "match", "count", "age"}
    known = np.isfinite(layers["traversability"])
    assert ((values.reshape(known.shape) == -1) == ~known).all()  # min_match 0: unknown only where unobserved
    assert (layers["cvar"][known] <= layers["traversability"][known] + 1e-6).all()
    assert np.isnan(layers["count"][~known]).all() and (layers["age"][known] == 0).all()


def test_the_question_a_fusion_asks_leaves_with_the_frames_outputs_on_the_question_key() -> None:
    """The hook runs under the grid's lock (it sees the grid as fused) and only returns its question; the output
    builder emits it beside the grid, and a fusion that asks nothing adds nothing."""
    grid = {"source": "cam", "intrinsics": {"fx": 40, "fy": 40, "cx": 32, "cy": 24, "width": 64, "height": 48},
            "mount": {"z": 1.0, "pitch": 0.5}, "size_m": 6.0, "resolution_m": 0.5}  # fmt: skip
    settings = ServiceSettings.model_validate({"grids": [grid], "preview": False})
    question = OperatorQuestion(id="cam-1", source="cam", stamp=1.0, reason="novel", region=(0.0, 0.0, 1.0, 1.0),
                                cells=[(0.5, 0.5)], concepts=[], anchor_set_version="v")  # fmt: skip
    asked: list[bool] = []

    def after_fusion(fused, camera, image):  # type: ignore[no-untyped-def]
        asked.append(fused.lock.locked() and int(fused.grid.known.sum()) > 0)
        return question if len(asked) == 1 else None

    grids = GridOutputs(settings.grids, 13, "test", settings.risk, after_fusion=after_fusion)
    builder, done = OutputBuilder(settings, "fake"), processed("cam")
    built = []
    for _ in range(2):
        fused = grids.fuse("cam", done.record, done.result.maps.weights, done.result.maps.match)
        built.append({output.key: output for output in builder.build(replace(done, grid=fused))})
    assert asked == [True, True]
    assert built[0]["gcdtrav/out/cam/question"].payload == question.pack()
    assert built[0]["gcdtrav/out/cam/question"].encoding == "msgpack"
    assert "gcdtrav/out/cam/question" not in built[1] and "gcdtrav/out/cam/grid" in built[1]
