"""The grid's 1.2 layers on the wire: an older writer's GridMessage still decodes (layers None), an older
reader still reads a new one, and the client's Grid decodes every layer as the service encoded it."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from gcdtrav.client.client import Grid
from gcdtrav.schemas.images import (
    AGE_NEVER,
    decode_age_png,
    encode_age_png,
    encode_count_png,
    encode_map_png16,
)
from gcdtrav.schemas.messages import GridHeader, GridMessage
from gcdtrav.schemas.strict import WireModel

OLD_HEADER = {  # a 1.1 writer's header: none of alpha, tau, expired_cells, age_s
    "source": "cam", "seq": 4, "stamp": 10.0, "frame_id": "odom", "origin": (0.0, 0.0), "resolution": 0.5,
    "cells": 2, "robot": (0.0, 0.0, 0.0), "anchor_set_version": "v", "resets": 0, "known_cells": 3, "instance": "a",
}  # fmt: skip
COUNT = np.array([[1, 0], [2, 3]])
T = np.array([[0.25, 0.0], [0.5, 1.0]], np.float32)


def old_payload() -> bytes:
    fields = {
        "schema_version": "1.1",
        "header": OLD_HEADER,
        "traversability_png": encode_map_png16(T),
        "uncertainty_png": encode_map_png16(T / 2),
        "count_png": encode_count_png(COUNT),
    }
    return msgpack.packb(fields, use_bin_type=True)


def new_message() -> GridMessage:
    age = np.array([[0.0, math.nan], [1.25, 6553.4 * 2]])
    return GridMessage(
        header=GridHeader.model_validate(OLD_HEADER | {"alpha": 0.1, "tau": 0.3, "expired_cells": 0, "age_s": 0.2}),
        traversability_png=encode_map_png16(T),
        uncertainty_png=encode_map_png16(T / 2),
        count_png=encode_count_png(COUNT),
        cvar_png=encode_map_png16(T / 4),
        p_below_png=encode_map_png16(1 - T),
        match_png=encode_map_png16(np.full((2, 2), 0.5)),
        age_png=encode_age_png(age),
    )


def test_an_older_writers_grid_decodes_without_the_layers() -> None:
    grid = Grid.from_payload(old_payload())
    assert grid.cvar is None and grid.p_below is None and grid.match is None and grid.age is None
    assert grid.header.alpha is None and grid.header.expired_cells is None and grid.header.age_s is None
    assert grid.traversability[1, 0] == pytest.approx(0.5, abs=1e-4) and math.isnan(grid.traversability[0, 1])
    assert grid.planning_layers().keys() == {"traversability"}


class GridMessage11(WireModel):
    """GridMessage as a 1.1 reader knows it."""

    schema_version: str
    header: dict[str, object]
    traversability_png: bytes
    uncertainty_png: bytes
    count_png: bytes


def test_an_older_reader_reads_a_new_grid() -> None:
    old = GridMessage11.model_validate(msgpack.unpackb(new_message().pack(), raw=False))
    assert old.traversability_png == new_message().traversability_png and old.header["cells"] == 2


def test_the_client_decodes_every_layer_with_unknown_cells_nan() -> None:
    grid = Grid.from_payload(new_message().pack())
    assert grid.header.alpha == 0.1 and grid.header.tau == 0.3 and grid.header.age_s == 0.2
    assert grid.cvar is not None and grid.p_below is not None and grid.match is not None and grid.age is not None
    assert grid.cvar[1, 1] == pytest.approx(0.25, abs=1e-4) and math.isnan(grid.cvar[0, 1])
    assert grid.p_below[0, 0] == pytest.approx(0.75, abs=1e-4) and math.isnan(grid.match[0, 1])
    # age: never observed NaN, tenths of a second, capped one step below the "never" value
    assert math.isnan(grid.age[0, 1]) and grid.age[1, 0] == pytest.approx(1.2) and grid.age[0, 0] == 0.0
    assert grid.age[1, 1] == pytest.approx((AGE_NEVER - 1) * 0.1)


def test_age_png_round_trip_at_its_edges() -> None:
    ages = np.array([[0.0, 0.04, 0.05, 6553.4, 1e9, math.nan, -1.0]])
    decoded = decode_age_png(encode_age_png(ages))
    np.testing.assert_allclose(decoded[0, :5], [0.0, 0.0, 0.0, 6553.4, 6553.4], atol=1e-3)  # 0.05: half to even
    assert math.isnan(decoded[0, 5]) and decoded[0, 6] == 0.0
