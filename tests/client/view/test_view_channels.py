"""What a Foxglove client of `gcdtrav view` gets, with a stand-in service (view_fakes): the anchor set when
it subscribes late, grid channels only for sources with a grid, T/U at the camera's aspect."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterator

import cv2
import numpy as np
import pytest

pytest.importorskip("foxglove", reason="the view extra: pip install 'gcdtrav[view]'")
pytest.importorskip("websockets")

from foxglove_ws import FoxgloveClient, protobuf_fields
from gcdtrav.client.view import viewer as viewer_module
from gcdtrav.client.view.pictures import LEGEND_WIDTH, MIN_HEIGHT, map_with_legend
from gcdtrav.client.view.viewer import Viewer, ViewOptions
from view_fakes import PAPER, FakeClient, grid_payload, maps_payload
from zenoh_helpers import wait_until

ANCHORS = "/gcdtrav/anchors"


@pytest.fixture()
def fake() -> FakeClient:
    return FakeClient()


def viewer_of(fake: FakeClient, status_period_s: float = 30.0) -> Viewer:
    """A started viewer; with the default period it polls the service once, at the start."""
    return Viewer(fake, ViewOptions(port=0, status_period_s=status_period_s)).start()  # type: ignore[arg-type]


@pytest.fixture()
def viewer(fake: FakeClient) -> Iterator[Viewer]:
    running = viewer_of(fake)
    yield running
    running.close()


async def anchors_seen_by_a_late_subscriber(url: str) -> dict:
    fox = await FoxgloveClient.connect(url)
    await fox.until(lambda: ANCHORS in fox.channels)
    await fox.subscribe(ANCHORS)
    await fox.until(lambda: bool(fox.received(ANCHORS)))
    await fox.close()
    return json.loads(fox.received(ANCHORS)[0])


def test_a_client_that_subscribes_after_the_anchor_set_was_sent_still_gets_it(viewer: Viewer) -> None:
    assert wait_until(lambda: viewer.logged[ANCHORS] == 1, 30)  # sent once; the next poll is 30 s away
    reply = asyncio.run(anchors_seen_by_a_late_subscriber(viewer.url))
    assert reply["version"] == PAPER.version and len(reply["anchor_set"]["anchors"]) == len(PAPER)


def test_the_anchor_set_is_sent_again_periodically(fake: FakeClient, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(viewer_module, "ANCHORS_REPEAT_S", 0.2)
    running = viewer_of(fake, status_period_s=0.1)
    try:
        assert wait_until(lambda: running.logged[ANCHORS] >= 3, 30)  # unchanged, yet sent again
        assert fake.anchor_queries == 1  # from what the viewer holds: no query per repeat
    finally:
        running.close()


async def topics_and_picture(viewer: Viewer, fake: FakeClient) -> tuple[set[str], bytes]:
    fox = await FoxgloveClient.connect(viewer.url)
    await fox.until(lambda: {"/gcdtrav/cam/traversability", "/gcdtrav/yard/grid"} <= set(fox.channels))
    await fox.subscribe("/gcdtrav/cam/traversability")
    fake.session.put("gcdtrav/out/cam/maps", maps_payload("cam", (8, 8), (160, 80), seq=1))
    await fox.until(lambda: bool(fox.received("/gcdtrav/cam/traversability")))
    await fox.close()
    return set(fox.channels), protobuf_fields(fox.received("/gcdtrav/cam/traversability")[-1])[2][0]


def test_grid_channels_only_for_sources_with_a_grid_and_maps_at_the_camera_aspect(
    viewer: Viewer, fake: FakeClient
) -> None:
    fake.session.put("gcdtrav/out/cam/maps", maps_payload("cam", (8, 8), (160, 80)))
    fake.session.put("gcdtrav/out/yard/maps", maps_payload("yard", (8, 8), (80, 80)))
    fake.session.put("gcdtrav/out/yard/grid", grid_payload("yard"))
    topics, png = asyncio.run(topics_and_picture(viewer, fake))

    assert {"/gcdtrav/cam/traversability", "/gcdtrav/cam/status", "/gcdtrav/yard/grid"} <= topics
    assert not {"/gcdtrav/cam/grid", "/gcdtrav/cam/preview", "/gcdtrav/cam/camera"} & topics
    picture = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    height, width = picture.shape[0], picture.shape[1] - LEGEND_WIDTH
    assert height >= MIN_HEIGHT and width == 2 * height  # a square map of a 2:1 camera image, drawn 2:1


def test_map_pictures_take_the_image_aspect_and_keep_whole_cells() -> None:
    square = np.linspace(0, 1, 22 * 22, dtype=np.float32).reshape(22, 22)
    wide = map_with_legend(square, "T", image_size=(640, 320))
    assert wide.shape[0] == 22 * 12 and wide.shape[1] - LEGEND_WIDTH == 2 * 22 * 12
    tall = map_with_legend(square, "U", image_size=(300, 600))
    assert tall.shape[1] - LEGEND_WIDTH == 22 * 12 // 2
    assert map_with_legend(square, "T").shape[1] - LEGEND_WIDTH == 22 * 12  # no image size: the map's own


def test_nothing_is_sent_before_the_anchor_set_is_known(fake: FakeClient) -> None:
    idle = Viewer(fake, ViewOptions(port=0))  # type: ignore[arg-type]
    try:
        idle.send_anchors()  # synchronous, and the idle viewer has no threads that could send it later
        assert idle.logged[ANCHORS] == 0
    finally:
        idle.close()
