"""grid_map_msgs/GridMap CDR: the cells land where grid_map's own index maths puts them; type hash and graph
token (tests/service/runtime/test_grid_outputs.py: the grid's CDR outputs on their keys and ROS topics)."""

from __future__ import annotations

import numpy as np
import pytest
from gcdtrav.schemas.messages import GridHeader

pytest.importorskip("rosbags")

from gcdtrav.service.ros import cdr as ros
from gcdtrav.service.ros.grid_map import (
    grid_map_cdr,
    to_grid_map_order,
)

from tools.ros_fixtures import decode_grid_map, from_grid_map_order

GRID_MAP_HASH = "RIHS01_343b0e72887541beda6b035cc053f2d6fffaad9d6dcb2773c15a808dfca31fde"


def header(origin: tuple[float, float], cells: int, resolution: float) -> GridHeader:
    return GridHeader(
        source="cam", seq=3, stamp=12.25, frame_id="odom", origin=origin, resolution=resolution, cells=cells,
        anchor_set_version="v", resets=0, known_cells=1, instance="test",
    )  # fmt: skip


def grid_map_position(a: int, b: int, message: object) -> tuple[float, float]:
    """grid_map_core's getPositionFromIndex with start index (0, 0) (GridMapMath.cpp): position = map position
    + (length / 2 - resolution / 2) - resolution * index, per axis; index (a, b) = (along x, along y)."""
    info = message.info  # type: ignore[attr-defined]
    r = info.resolution
    x = info.pose.position.x + info.length_x / 2 - r / 2 - r * a
    y = info.pose.position.y + info.length_y / 2 - r / 2 - r * b
    return x, y


def test_every_cell_lands_where_grid_maps_index_maths_puts_it() -> None:
    cells, r, origin = 5, 0.5, (-1.0, 2.0)
    grid = np.arange(cells * cells, dtype=np.float32).reshape(cells, cells)  # every cell its own value
    grid[1, 3] = 1000.0  # a known cell: row i = 1 (y), column j = 3 (x): centre (0.75, 2.75)
    grid[4, 0] = np.nan  # unknown: grid_map's "no data"
    payload = grid_map_cdr(header(origin, cells, r), {"traversability": grid, "count": grid * 2}, ["traversability"])
    message = ros.typestore().deserialize_cdr(payload, ros.GRID_MAP)
    assert list(message.layers) == ["traversability", "count"] and list(message.basic_layers) == ["traversability"]
    assert (
        message.header.frame_id == "odom"
        and message.header.stamp.sec == 12
        and message.header.stamp.nanosec == 250_000_000
    )
    assert (message.info.length_x, message.info.length_y, message.info.resolution) == (2.5, 2.5, 0.5)
    assert (message.info.pose.position.x, message.info.pose.position.y) == (0.25, 3.25)  # the CENTRE
    assert (message.outer_start_index, message.inner_start_index) == (0, 0)
    column, row = message.data[0].layout.dim
    assert (column.label, column.size, column.stride) == ("column_index", cells, cells * cells)
    assert (row.label, row.size, row.stride) == ("row_index", cells, cells)
    data = np.asarray(message.data[0].data)
    # column-major: element (a, b) of the (size_x, size_y) matrix is data[b * size_x + a] (getLinearIndexFromIndex)
    size_x = row.size
    k_known = int(np.flatnonzero(data == 1000.0)[0])
    a, b = k_known % size_x, k_known // size_x
    assert grid_map_position(a, b, message) == pytest.approx((0.75, 2.75))
    for k in range(cells * cells):  # every cell: the value at grid_map's position is gcdtrav's cell there
        x, y = grid_map_position(k % size_x, k // size_x, message)
        i, j = int(np.floor((y - origin[1]) / r)), int(np.floor((x - origin[0]) / r))
        np.testing.assert_equal(data[k], grid[i, j])
    np.testing.assert_equal(np.asarray(message.data[1].data), data * 2)
    _, layers = decode_grid_map(payload)
    np.testing.assert_array_equal(layers["traversability"], grid)


def test_storage_order_round_trips_a_grid_that_is_not_square() -> None:
    grid = np.arange(15, dtype=np.float32).reshape(3, 5)  # 3 rows (y), 5 columns (x)
    data = to_grid_map_order(grid)
    assert data[0] == grid[2, 4]  # index (0, 0): the max-x, max-y corner
    assert data[1] == grid[2, 3]  # index (1, 0): one cell along -x (a runs fastest, column-major)
    assert data[5] == grid[1, 4]  # index (0, 1): one cell along -y
    np.testing.assert_array_equal(from_grid_map_order(data, cells_x=5, cells_y=3), grid)


def test_grid_map_type_hash_and_graph_token() -> None:
    from gcdtrav.service.bus.ros_graph import GRID_QOS, Entity, NodeName, TopicInfo

    assert ros.type_hash(ros.GRID_MAP) == GRID_MAP_HASH
    camera = ros.RosTopic("/cam/image_raw", ros.IMAGE, "rmw_zenoh", type_hash=ros.type_hash(ros.IMAGE))
    topic = camera.derived("/cam/image_raw/gcdtrav/grid/gridmap", ros.GRID_MAP)
    assert (
        ros.topic_key(topic)
        == f"0/cam/image_raw/gcdtrav/grid/gridmap/grid_map_msgs::msg::dds_::GridMap_/{GRID_MAP_HASH}"
    )
    entity = Entity("zid", 0, 5, "MP", NodeName(0, "/", "gcdtrav"), TopicInfo.of(topic, GRID_QOS))
    assert entity.token.endswith(
        f"/MP/%/%/gcdtrav/%cam%image_raw%gcdtrav%grid%gridmap/grid_map_msgs::msg::dds_::GridMap_/{GRID_MAP_HASH}/:1:,1:,:,:,,"
    )
    humble = ros.RosTopic("/cam/image_raw", ros.IMAGE, "rmw_zenoh", type_hash=ros.HUMBLE_HASH)
    assert humble.derived("/x", ros.GRID_MAP).type_hash == ros.HUMBLE_HASH
