"""The one table of grid layers (schemas/grid_layers.py): the message, the service's encoder, the client's
decoder and the viewer all follow it, so a layer added to it reaches each of them."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from gcdtrav.client.client import Grid
from gcdtrav.client.view.pictures import SCALES
from gcdtrav.schemas.grid_layers import GRID_LAYERS, decode_layers, encode_layers
from gcdtrav.schemas.messages import GridHeader, GridMessage
from gcdtrav.service.grid.layers import GridLayers

HEADER = GridHeader(
    source="cam", seq=1, stamp=5.0, frame_id="odom", origin=(0.0, 0.0), resolution=0.5, cells=2,
    robot=(0.0, 0.0, 0.0), anchor_set_version="v", resets=0, known_cells=3, instance="a",
)  # fmt: skip


def layers() -> GridLayers:
    t = np.array([[0.25, np.nan], [0.5, 1.0]], np.float32)
    count = np.array([[1, 0], [2, 300]], np.int64)
    age = np.array([[0.0, np.nan], [1.25, 3.0]])
    speed = np.array([[0.3, 0.3], [1.0, 0.65]], np.float32)  # configured where unknown: never NaN
    return GridLayers(t, t / 2, t / 4, 1 - t, np.full((2, 2), 0.5, np.float32), count, age, t, 0.1, 0.3, 0.3, speed)


def test_every_layer_of_the_table_is_a_message_field_and_every_layer_field_a_row() -> None:
    fields = {name for name in GridMessage.model_fields if name.endswith("_png")}
    assert fields == {layer.field for layer in GRID_LAYERS}
    assert len({layer.name for layer in GRID_LAYERS}) == len(GRID_LAYERS)


def test_grid_map_layer_order_is_the_tables_and_unchanged() -> None:
    expected = ("traversability", "uncertainty", "cvar", "p_below", "match", "count", "age", "speed")
    assert tuple(layers().float_layers()) == expected == tuple(layer.name for layer in GRID_LAYERS)
    without_speed = replace(layers(), speed=None)  # a grid without speed: its layers as before 1.5
    assert tuple(without_speed.float_layers()) == expected[:-1]
    message = GridMessage.model_validate({"header": HEADER, **encode_layers(without_speed.values())})
    assert message.speed_png is None and Grid.from_payload(message.pack()).speed is None


def test_every_drawn_layer_has_a_colour_scale_in_the_viewer() -> None:
    assert all(layer.scale in SCALES for layer in GRID_LAYERS if layer.scale is not None)


def test_the_client_decodes_every_layer_the_service_encodes() -> None:
    source = layers()
    message = GridMessage.model_validate({"header": HEADER, **encode_layers(source.values())})
    grid = Grid.from_payload(message.pack())
    assert set(grid.layers) == {layer.name for layer in GRID_LAYERS} == set(decode_layers(message))
    for layer in GRID_LAYERS:
        expected = np.asarray(getattr(source, layer.name), np.float64)
        if layer.codec.unknown_nan:
            expected = np.where(source.count > 0, expected, np.nan)
        np.testing.assert_allclose(grid.layers[layer.name], expected, atol=0.05, err_msg=layer.name)
    assert grid.count[1, 1] == 300 and math.isnan(grid.uncertainty[0, 1]) and grid.age is not None
