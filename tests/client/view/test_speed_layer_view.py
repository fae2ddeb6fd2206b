"""The viewer shows the speed layer of a grid that has one: its channel, colours on every cell (the speed of an
unknown cell is configured, never NaN) and a picture with a legend; a grid without it has no such channel."""

from __future__ import annotations

import numpy as np
from gcdtrav.client.client import Grid
from gcdtrav.client.view.grid_layers import LAYER_CELL_BYTES, layer_cells, layer_picture, layer_values
from gcdtrav.client.view.pictures import colour_map
from gcdtrav.schemas.grid_layers import encode_layers
from gcdtrav.schemas.messages import GridHeader, GridMessage

HEADER = GridHeader(
    source="cam", seq=1, stamp=5.0, frame_id="odom", origin=(0.0, 0.0), resolution=0.5, cells=2,
    robot=(0.5, 0.5, 0.0), anchor_set_version="v", resets=0, known_cells=3, instance="a",
)  # fmt: skip


def grid(with_speed: bool) -> Grid:
    t = np.array([[0.25, np.nan], [0.5, 1.0]], np.float32)
    values = {
        "traversability": t, "uncertainty": t / 2, "cvar": t, "p_below": 1 - t, "match": t,
        "count": np.array([[1, 0], [2, 3]]), "age": np.zeros((2, 2)),
    }  # fmt: skip
    if with_speed:
        values["speed"] = np.array([[0.3, 0.3], [1.0, 0.65]], np.float32)  # the unknown cell at the floor
    message = GridMessage.model_validate({"header": HEADER, **encode_layers(values)})
    return Grid.from_payload(message.pack())


def test_the_speed_layer_is_a_channel_coloured_on_every_cell_slow_red_fast_green() -> None:
    kind, values = layer_values(grid(with_speed=True))["speed"]
    assert kind == "speed" and np.isfinite(values).all()
    cells = np.frombuffer(layer_cells(values, kind), np.uint8).reshape(2, 2, LAYER_CELL_BYTES)
    assert (cells[..., 7] == 255).all()  # opaque: known speed everywhere
    colours = colour_map(values, kind)
    slow, fast = colours[0, 0].astype(int), colours[1, 0].astype(int)
    assert slow[0] > slow[1] and fast[1] > fast[0]
    picture = layer_picture(values, kind, HEADER)
    assert picture.ndim == 3 and picture.shape[2] == 3


def test_a_grid_without_speed_has_no_speed_channel() -> None:
    assert "speed" not in layer_values(grid(with_speed=False))
