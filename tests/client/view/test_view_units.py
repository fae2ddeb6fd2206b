"""The viewer's pure parts: anchor set <-> Foxglove parameters, latest-only slots, the grid's cell layout."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from gcdtrav.client.client import Grid
from gcdtrav.client.view.anchor_parameters import JSON_PARAMETER, anchor_parameters, apply_parameters
from gcdtrav.client.view.latest import LatestSlots
from gcdtrav.client.view.pictures import GRID_CELL_BYTES, grid_cells, map_with_legend
from gcdtrav.schemas.anchors import AnchorSet, AnchorSetError, default_anchor_set
from gcdtrav.schemas.messages import GridHeader

PAPER = default_anchor_set()


def rejected(changes: dict[str, object]) -> list[str]:
    with pytest.raises(AnchorSetError) as caught:
        apply_parameters(PAPER, changes)
    return caught.value.messages


def test_parameters_round_trip_the_set() -> None:
    values = anchor_parameters(PAPER)
    assert values["anchors/name"] == "paper" and values["anchors/12/concept"] == "concrete"
    assert values["anchors/12/position"] == 1.0 and values["anchors/12/width"] is None  # null, as the set says
    assert AnchorSet.from_text(str(values[JSON_PARAMETER])) == PAPER
    assert apply_parameters(PAPER, {name: values[name] for name in values if name != JSON_PARAMETER}) == PAPER


def test_one_edit_changes_one_field_and_keeps_the_rest() -> None:
    moved = apply_parameters(PAPER, {"anchors/02/position": 0.25, "anchors/name": "edited"})
    assert moved.anchors[2].position == 0.25 and moved.name == "edited"
    assert [a for k, a in enumerate(moved.anchors) if k != 2] == [a for k, a in enumerate(PAPER.anchors) if k != 2]
    assert apply_parameters(PAPER, {"anchors/11/position": 1}).anchors[11].position == 1.0  # JSON ints are numbers


def test_a_width_is_null_until_set_and_null_sets_it_back() -> None:
    assert apply_parameters(PAPER, {"anchors/04/width": None}).anchors[4].width is None  # the shown value
    own = apply_parameters(PAPER, {"anchors/04/width": 0.05})
    assert own.anchors[4].width == 0.05 and anchor_parameters(own)["anchors/04/width"] == 0.05
    assert apply_parameters(own, {"anchors/04/width": None}).anchors[4].width is None
    assert apply_parameters(PAPER, {"anchors/04/width": 0.0}).anchors[4].width == 0.0  # 0 is a width, not null
    wider = apply_parameters(PAPER, {"anchors/default_width": 0.02})
    assert anchor_parameters(wider)["anchors/04/width"] is None and wider.widths[4] == 0.02


def test_problems_name_the_parameters() -> None:
    assert rejected({"anchors/02/position": 1.5})[0].startswith("anchors/02/position: position 1.5 is outside")
    assert rejected({"anchors/02/position": "far"}) == ["anchors/02/position: expected a number, got 'far'"]
    assert rejected({"anchors/02/position": True}) == ["anchors/02/position: expected a number, got True"]
    assert rejected({"anchors/02/position": 0.9})[0].startswith("anchors/02/position: anchors must be sorted")
    assert "appears more than once" in rejected({"anchors/03/concept": "water"})[0]
    assert rejected({"anchors/13/concept": "x"})[0].startswith("anchors/13/concept: no such parameter")
    assert rejected({"speed": 1})[0].startswith("speed: no such parameter")
    assert rejected({"anchors/default_width": -1})[0].startswith("anchors/default_width: default_width -1.0")
    both = rejected({"anchors/02/position": 1.5, "anchors/name": 7})
    assert [m.split(":")[0] for m in both] == ["anchors/name"]  # type problems first, before validation


def test_the_json_parameter_replaces_the_whole_set_or_nothing() -> None:
    two = '{"name": "two", "anchors": [{"concept": "lake", "position": 0}, {"concept": "road", "position": 1}]}'
    assert apply_parameters(PAPER, {JSON_PARAMETER: two}).concepts == ["lake", "road"]
    assert rejected({JSON_PARAMETER: '{"anchors": []}'})[0].startswith("anchors/json: anchors: an anchor set needs")
    assert rejected({JSON_PARAMETER: two, "anchors/name": "x"})[0].startswith("anchors/json replaces the whole set")
    assert rejected({JSON_PARAMETER: "{"})[0].startswith("anchors/json: not valid JSON or YAML")


def test_latest_slots_keep_the_newest_per_key_within_a_bound() -> None:
    slots: LatestSlots[str, int] = LatestSlots(max_keys=2)
    assert slots.put("a", 1) and slots.put("a", 2) and slots.put("b", 3)
    assert not slots.put("c", 4)  # a third key while two wait
    assert (slots.replaced, slots.refused) == (1, 1)
    assert slots.take_all(timeout=0) == {"a": 2, "b": 3}
    assert slots.take_all(timeout=0.01) == {} and slots.put("c", 5)  # taken: room again


def test_a_put_wakes_a_waiting_take() -> None:
    slots: LatestSlots[str, int] = LatestSlots(max_keys=4)
    threading.Timer(0.05, slots.put, ("a", 1)).start()
    assert slots.take_all(timeout=5) == {"a": 1}


def test_grid_cells_hold_t_u_count_and_t_colours() -> None:
    t = np.array([[0.0, 1.0], [np.nan, 0.5]], np.float32)
    count = np.array([[3, 1], [0, 70000]], np.int64)
    header = GridHeader(
        source="cam", seq=0, stamp=0.0, frame_id="odom", origin=(0.0, 0.0), resolution=0.5, cells=2,
        anchor_set_version="x", resets=0, known_cells=3, instance="i",
    )  # fmt: skip
    grid = Grid(header, {"traversability": t, "uncertainty": t / 2, "count": count})
    cells = np.frombuffer(grid_cells(grid), np.uint8).reshape(2, 2, GRID_CELL_BYTES)
    assert np.array_equal(cells[..., 0:4].copy().view("<f4")[..., 0], t, equal_nan=True)
    assert np.array_equal(cells[..., 4:8].copy().view("<f4")[..., 0], t / 2, equal_nan=True)
    assert cells[..., 8:12].copy().view("<u4")[..., 0].tolist() == [[3, 1], [0, 70000]]
    assert cells[0, 0, 12] > cells[0, 0, 13] and cells[0, 1, 13] > cells[0, 1, 12]  # red at T 0, green at T 1
    assert cells[..., 15].tolist() == [[255, 255], [0, 255]]  # unknown cells transparent


def test_maps_get_a_legend_and_small_maps_are_enlarged() -> None:
    picture = map_with_legend(np.linspace(0, 1, 96 * 64, dtype=np.float32).reshape(96, 64), "T")
    assert picture.shape[0] == 288 and picture.shape[1] > 3 * 64
    assert tuple(picture[0, 0]) != tuple(picture[-1, 0])  # the colour follows T


def test_camera_images_are_told_apart_as_the_service_does() -> None:
    """A bare PNG, JPEG or BMP camera is shown (a BMP re-encoded as JPEG), an envelope unwrapped."""
    import cv2
    from gcdtrav.client.view.viewer import camera_image
    from gcdtrav.schemas.images import encode_jpeg, encode_png
    from gcdtrav.schemas.messages import ImageEnvelope

    image = np.full((20, 30, 3), 120, np.uint8)
    png, jpeg = encode_png(image), encode_jpeg(image)
    bmp = cv2.imencode(".bmp", image)[1].tobytes()
    assert camera_image(png)[:2] == (png, "png") and camera_image(jpeg)[:2] == (jpeg, "jpeg")
    data, kind, _, _ = camera_image(bmp)
    assert kind == "jpeg" and cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR).shape == (20, 30, 3)
    wrapped = ImageEnvelope(stamp=5.0, frame_id="cam", encoding="png", width=30, height=20, data=png).pack()
    assert camera_image(wrapped) == (png, "png", 5.0, "cam")
