"""What a Foxglove client of `gcdtrav view` gets, with a stand-in service (view_fakes): the anchor set when
it subscribes late."""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import Iterator

import pytest

pytest.importorskip("foxglove", reason="the view extra: pip install 'gcdtrav[view]'")
pytest.importorskip("websockets")

from foxglove_ws import FoxgloveClient
from gcdtrav.client.view import viewer as viewer_module
from gcdtrav.client.view.viewer import Viewer, ViewOptions
from view_fakes import PAPER, FakeClient
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
    await fox.until(lambda: bool(fox.received(ANCHORS)), timeout=5.0)
    await fox.close()
    return json.loads(fox.received(ANCHORS)[0])


def test_a_client_that_subscribes_after_the_anchor_set_was_sent_still_gets_it(viewer: Viewer) -> None:
    assert wait_until(lambda: viewer.logged[ANCHORS] == 1, 10)  # sent once; the next poll is 30 s away
    reply = asyncio.run(anchors_seen_by_a_late_subscriber(viewer.url))
    assert reply["version"] == PAPER.version and len(reply["anchor_set"]["anchors"]) == len(PAPER)


def test_the_anchor_set_is_sent_again_periodically(fake: FakeClient, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(viewer_module, "ANCHORS_REPEAT_S", 0.2)
    running = viewer_of(fake, status_period_s=0.1)
    try:
        assert wait_until(lambda: running.logged[ANCHORS] >= 3, 10)  # unchanged, yet sent again
        assert fake.anchor_queries == 1  # from what the viewer holds: no query per repeat
    finally:
        running.close()


def test_nothing_is_sent_before_the_anchor_set_is_known(fake: FakeClient) -> None:
    idle = Viewer(fake, ViewOptions(port=0))  # type: ignore[arg-type]
    try:
        idle.send_anchors()
        time.sleep(0.05)
        assert idle.logged[ANCHORS] == 0
    finally:
        idle.close()
