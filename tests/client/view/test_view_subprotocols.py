"""Which WebSocket subprotocols `gcdtrav view` accepts: foxglove-sdk's server takes `foxglove.sdk.v1` only (a
constant in its Rust handshake, no setting), so docs/view.md names the viewer versions that offer it; this
checks that what it says holds."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from pathlib import Path

import pytest

pytest.importorskip("foxglove", reason="the view extra: pip install 'gcdtrav[view]'")
websockets = pytest.importorskip("websockets")

from gcdtrav.client.view.viewer import Viewer, ViewOptions  # noqa: E402
from view_fakes import FakeClient  # noqa: E402

DOCS = Path(__file__).resolve().parents[3] / "docs" / "view.md"
REFUSAL = "Missing expected sec-websocket-protocol header"


@pytest.fixture()
def viewer() -> Iterator[Viewer]:
    with Viewer(FakeClient(), ViewOptions(port=0)) as running:  # type: ignore[arg-type]
        yield running


async def handshake(url: str, subprotocols: list[str]) -> str:
    async with websockets.connect(url, subprotocols=subprotocols) as websocket:
        return str(websocket.subprotocol)


def test_subprotocols_as_docs_view_md_says(viewer: Viewer) -> None:
    """foxglove-sdk 0.30 accepts foxglove.sdk.v1 only: docs/view.md names the viewers that offer it."""
    assert asyncio.run(handshake(viewer.url, ["foxglove.sdk.v1"])) == "foxglove.sdk.v1"
    lichtblick = ["foxglove.websocket.v1", "foxglove.sdk.v1"]  # Lichtblick v1.22.1+ offers both
    assert asyncio.run(handshake(viewer.url, lichtblick)) == "foxglove.sdk.v1"
    with pytest.raises(websockets.exceptions.InvalidStatus) as refused:  # ws-protocol 0.8's client, old Lichtblick
        asyncio.run(handshake(viewer.url, ["foxglove.websocket.v1"]))
    assert refused.value.response.status_code == 400
    assert refused.value.response.body == REFUSAL.encode()
    docs = DOCS.read_text()
    assert f"HTTP 400 `{REFUSAL}`" in docs and "v1.22.1 or later" in docs
