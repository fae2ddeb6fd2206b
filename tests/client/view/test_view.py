"""`gcdtrav view` against a real service on loopback: a Foxglove WebSocket client subscribes, receives a T
image and the grid, edits the anchor set through parameters (accepted, then rejected), and the MCAP files
read back with the mcap library hold exactly the messages the viewer sent."""

from __future__ import annotations

import asyncio
import json
import signal
import subprocess
import sys
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import camera_grid, textured_image, torch_free_gcdtrav
from zenoh_helpers import connecting_config, frame_counted, service_reachable, subscribed_elsewhere, wait_until

pytest.importorskip("torch")
pytest.importorskip("foxglove", reason="the view extra: pip install 'gcdtrav[view]'")
mcap_reader = pytest.importorskip("mcap.reader")
pytest.importorskip("websockets")

from foxglove_ws import FoxgloveClient, double, fixed32, protobuf_fields  # noqa: E402
from gcdtrav.client import Grid, TraversabilityClient  # noqa: E402
from gcdtrav.client.view.pictures import GRID_CELL_BYTES, GRID_FIELDS, LEGEND_WIDTH, MIN_HEIGHT  # noqa: E402
from gcdtrav.client.view.viewer import Viewer, ViewOptions  # noqa: E402
from gcdtrav.schemas.anchors import default_anchor_set  # noqa: E402
from gcdtrav.schemas.messages import Pose2D  # noqa: E402
from gcdtrav.schemas.settings import ServiceSettings  # noqa: E402
from gcdtrav.service.bus.node import TraversabilityService  # noqa: E402

from tools.loopback import in_process_service  # noqa: E402

GRID_CELLS = 32
LAYOUT = Path(__file__).resolve().parents[3] / "examples" / "foxglove" / "gcdtrav-layout.json"


def grid_settings(state_dir: Path) -> ServiceSettings:
    # max_frame_age_s off: frames are stamped 100 s after the epoch
    return ServiceSettings.model_validate(
        {"state_dir": str(state_dir), "instance": "view-1", "grids": [camera_grid()], "max_frame_age_s": None}
    )


@pytest.fixture()
def service(tiny_backend, tmp_path: Path) -> Iterator[tuple[TraversabilityService, int]]:  # type: ignore[no-untyped-def]
    with in_process_service(tiny_backend, grid_settings(tmp_path / "state")) as running:
        yield running


def inputs_known(client: TraversabilityClient) -> None:
    """The service's pose and image subscriptions known to the client's session: what it puts arrives."""
    assert subscribed_elsewhere(client.session, "robot/pose") and subscribed_elsewhere(client.session, "gcdtrav/in/cam")


def drive(client: TraversabilityClient, step: int) -> None:
    """One pose and one camera frame of source 'cam' (stamped 100 + step). The pose goes first on the same
    session; the grid's fusion waits for a pose of the frame's stamp besides."""
    client.session.put("robot/pose", Pose2D(stamp=100.0 + step, x=0.25 * step, y=0.0, yaw=0.0).pack())
    client.publish_image("cam", textured_image(60, 80, seed=step), stamp=100.0 + step, frame_id="front")


def stamped(image: bytes) -> int:
    """The seconds of a foxglove.CompressedImage's timestamp (field 1: Timestamp, its field 1 seconds)."""
    return int(protobuf_fields(protobuf_fields(image)[1][0]).get(1, [0])[0])


def layout_topics(path: Path) -> set[str]:
    """Every topic the saved Foxglove layout's panels show."""
    topics: set[str] = set()
    for config in json.loads(path.read_text())["configById"].values():
        topics.update(config.get("topics", {}))
        topics.update(
            value
            for value in (
                config.get("imageMode", {}).get("imageTopic"),
                config.get("topicPath"),
                config.get("topicToRender"),
            )
            if value
        )
    return topics


def read_mcap(files: list[Path]) -> tuple[Counter[str], dict[str, tuple[str, str]]]:
    """Messages per topic over all files, and each topic's (message encoding, schema name)."""
    counts: Counter[str] = Counter()
    kinds: dict[str, tuple[str, str]] = {}
    for path in files:
        with path.open("rb") as stream:
            reader = mcap_reader.make_reader(stream)
            assert reader.get_summary() is not None, f"{path} was not closed cleanly"
            for schema, channel, _ in reader.iter_messages():
                counts[channel.topic] += 1
                kinds[channel.topic] = (channel.message_encoding, schema.name if schema else "")
    return counts, kinds


async def watch_and_steer(url: str, client: TraversabilityClient, running: TraversabilityService) -> dict:
    """The Foxglove side of the test; returns what it saw for the assertions and the report."""
    fox = await FoxgloveClient.connect(url)
    seen: dict = {"subprotocol": fox.websocket.subprotocol}
    await fox.until(lambda: bool(fox.server_info))
    seen["capabilities"] = fox.server_info["capabilities"]
    drive(client, 0)
    topics = ["/gcdtrav/cam/traversability", "/gcdtrav/cam/grid", "/gcdtrav/log"]
    await fox.until(lambda: all(topic in fox.channels for topic in topics))  # step 0's maps and grid shown
    await fox.subscribe(*topics)
    for step in (1, 2):  # the next frame once this one's T is shown: the viewer keeps only the latest maps
        await asyncio.to_thread(drive, client, step)
        await fox.until(lambda s=step: any(stamped(image) == 100 + s for image in fox.received(topics[0])))
    await fox.until(lambda: bool(fox.received(topics[1])))
    seen["channels"] = {t: (c["encoding"], c["schemaName"], c["schemaEncoding"]) for t, c in fox.channels.items()}
    seen["t_image"] = protobuf_fields(fox.received(topics[0])[-1])
    seen["grid"] = protobuf_fields(fox.received(topics[1])[-1])

    await fox.send(op="subscribeParameterUpdates", parameterNames=[])
    await fox.send(op="getParameters", parameterNames=[], id="all")
    seen["parameters"] = await fox.parameters("all")

    await fox.send(op="setParameters", parameters=[{"name": "anchors/02/position", "value": 0.25}], id="good")
    seen["after_good"] = await fox.parameters("good")
    seen["version_after_good"] = running.pipeline.anchors.version
    seen["position_after_good"] = running.pipeline.anchors.anchors[2].position

    await fox.send(op="setParameters", parameters=[{"name": "anchors/02/position", "value": 1.5}], id="bad")
    seen["after_bad"] = await fox.parameters("bad")
    seen["version_after_bad"] = running.pipeline.anchors.version
    logs = fox.received("/gcdtrav/log")
    await fox.until(lambda: any(b"not changed" in message for message in logs))
    seen["rejection"] = next(protobuf_fields(m) for m in logs if b"not changed" in m)
    seen["status_ops"] = fox.ops_named("status")
    await fox.close()
    return seen


def test_foxglove_client_sees_maps_grid_and_steers_the_anchor_set(service, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    running, port = service
    record = tmp_path / "record"
    options = ViewOptions(port=0, record=record, record_file_bytes=64 * 1024, status_period_s=0.5)
    with TraversabilityClient(config=connecting_config(port), timeout=5.0) as client:
        assert wait_until(lambda: service_reachable(client), 30)
        inputs_known(client)
        grids: list[Grid] = []
        subscriber = client.subscribe_grid("cam", grids.append)
        with Viewer(client, options) as viewer:
            # the viewer's (and the test's: the same session) subscriptions known to the service
            for key in ("gcdtrav/out/cam/maps", "gcdtrav/out/cam/grid"):
                assert subscribed_elsewhere(running.session, key), key
            seen = asyncio.run(watch_and_steer(viewer.url, client, running))
            logged = Counter(viewer.logged)
            files = list(viewer.recorder.files) if viewer.recorder else []
        subscriber.undeclare()

    assert seen["subprotocol"] == "foxglove.sdk.v1" and "parameters" in seen["capabilities"]
    channels = seen["channels"]
    image = ("protobuf", "foxglove.CompressedImage", "protobuf")
    for name in ("camera", "preview", "traversability", "uncertainty"):
        assert channels[f"/gcdtrav/cam/{name}"] == image
    assert channels["/gcdtrav/cam/grid"] == ("protobuf", "foxglove.Grid", "protobuf")
    assert channels["/gcdtrav/log"] == ("protobuf", "foxglove.Log", "protobuf")
    assert channels["/gcdtrav/anchors"] == ("json", "gcdtrav.AnchorSetReply", "jsonschema")
    assert channels["/gcdtrav/status"] == ("json", "gcdtrav.ServiceStatuses", "jsonschema")
    assert channels["/gcdtrav/cam/status"] == ("json", "gcdtrav.SourceView", "jsonschema")
    assert layout_topics(LAYOUT) <= set(channels), "the shipped layout shows topics the viewer does not publish"

    # T: a PNG (CompressedImage fields 2 data, 3 format, 4 frame_id), the map enlarged beside its legend.
    t_image = seen["t_image"]
    assert t_image[3] == [b"png"] and t_image[4] == [b"front"]
    picture = cv2.imdecode(np.frombuffer(t_image[2][0], np.uint8), cv2.IMREAD_COLOR)
    assert picture.shape[0] >= MIN_HEIGHT and picture.shape[1] > LEGEND_WIDTH

    # The grid: 32 x 32 cells of T, U, count and colours, matching the service's own grid message.
    grid = seen["grid"]
    assert fixed32(grid[4][0]) == GRID_CELLS and fixed32(grid[7][0]) == GRID_CELL_BYTES
    assert fixed32(grid[6][0]) == GRID_CELLS * GRID_CELL_BYTES and grid[2] == [b"odom"]
    names = [protobuf_fields(f)[1][0].decode() for f in grid[8]]
    assert names == [name for name, _, _ in GRID_FIELDS] and names[:3] == ["T", "U", "count"]
    cell_size = protobuf_fields(grid[5][0])
    assert double(cell_size[1][0]) == pytest.approx(0.25)
    cells = np.frombuffer(grid[9][0], np.uint8).reshape(GRID_CELLS, GRID_CELLS, GRID_CELL_BYTES)
    count = cells[:, :, 8:12].copy().view("<u4")[:, :, 0]
    t = cells[:, :, 0:4].copy().view("<f4")[:, :, 0]
    service_grid = next(g for g in reversed(grids) if (g.count == count).all())
    known = count > 0
    assert known.any() and np.isnan(t[~known]).all()
    assert np.allclose(t[known], service_grid.traversability[known])
    assert (cells[:, :, 15][known] == 255).all() and (cells[:, :, 15][~known] == 0).all()

    # Parameters: the active set, one edit swapped on the service, a bad edit rejected naming the field.
    parameters = seen["parameters"]
    paper = default_anchor_set()
    assert parameters["anchors/name"] == "paper" and parameters["anchors/02/concept"] == "ice"
    assert parameters["anchors/02/position"] == pytest.approx(0.2)
    assert sum(name.endswith("/concept") for name in parameters) == len(paper)
    assert seen["position_after_good"] == 0.25 and seen["version_after_good"] != paper.version
    assert seen["after_good"]["anchors/02/position"] == pytest.approx(0.25)
    assert seen["after_bad"]["anchors/02/position"] == pytest.approx(0.25)  # unchanged
    assert seen["version_after_bad"] == seen["version_after_good"]
    rejection = seen["rejection"]
    assert rejection[2] == [4]  # Log level ERROR
    text = rejection[3][0].decode()
    assert "anchors/02/position: position 1.5 is outside [0, 1]" in text and seen["version_after_good"] in text
    assert any("anchors/02/position" in op["message"] and op["level"] == 2 for op in seen["status_ops"])

    # MCAP: rotated by size, every file closed cleanly, the same messages per topic as the viewer sent.
    counts, kinds = read_mcap(files)
    assert len(files) >= 2, f"{len(files)} file(s) of {[f.stat().st_size for f in files]} bytes"
    assert counts == logged and counts["/gcdtrav/cam/traversability"] >= 3
    assert kinds["/gcdtrav/cam/grid"] == ("protobuf", "foxglove.Grid")
    print("\nchannels:", channels, "\nparameters:", dict(list(parameters.items())[:6]), "...", len(parameters))
    print("mcap:", len(files), "files", dict(counts))


def gcdtrav_view(*args: str) -> subprocess.Popen[str]:
    """`gcdtrav view ARGS` with torch and transformers unimportable."""
    command = torch_free_gcdtrav("view", *args)
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


async def two_maps_and_a_status_shown(url: str, client: TraversabilityClient) -> None:
    """Step 0's maps, then step 1's, and a status, each sent by the viewer (to every sink: the MCAP file too)."""
    fox = await FoxgloveClient.connect(url)
    topics = ["/gcdtrav/cam/traversability", "/gcdtrav/status"]
    await fox.until(lambda: bool(fox.server_info))
    drive(client, 0)
    await fox.until(lambda: all(topic in fox.channels for topic in topics))  # step 0's T sent as it appeared
    await fox.subscribe(*topics)
    await asyncio.to_thread(drive, client, 1)  # after step 0's was shown: the viewer keeps only the latest
    await fox.until(lambda: any(stamped(image) == 101 for image in fox.received(topics[0])))
    await fox.until(lambda: bool(fox.received(topics[1])))
    await fox.close()


@pytest.mark.parametrize("stop_signal", [signal.SIGTERM, signal.SIGINT])
def test_gcdtrav_view_records_until_a_signal_and_closes_its_file(service, tmp_path: Path, stop_signal) -> None:  # type: ignore[no-untyped-def]
    running, port = service
    record = tmp_path / "record"
    flags = ["-m", "client", "-e", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"]
    view = gcdtrav_view("--port", "0", "--record", str(record), "--status-period", "0.3", *flags)
    try:
        assert view.stdout is not None
        first = view.stdout.readline()
        assert first.startswith("gcdtrav view: Foxglove WebSocket at ws://localhost:"), first + view.stderr.read()
        url = first.split(" at ")[1].split()[0]
        assert subscribed_elsewhere(running.session, "gcdtrav/out/cam/maps"), "the viewer's maps subscription"
        with TraversabilityClient(config=connecting_config(port), timeout=5.0) as client:
            inputs_known(client)
            asyncio.run(two_maps_and_a_status_shown(url, client))
        view.send_signal(stop_signal)
        out, err = view.communicate(timeout=30)
    finally:
        if view.poll() is None:
            view.kill()
    assert view.returncode == 0, err
    files = sorted(record.glob("*.mcap"))
    counts, _ = read_mcap(files)
    assert counts["/gcdtrav/cam/traversability"] >= 2 and counts["/gcdtrav/status"] >= 1
    summary = {line.split(": ")[0]: line.split(": ")[1] for line in out.splitlines() if line.startswith(str(record))}
    assert list(summary) == [str(files[0])]
    assert summary[str(files[0])].startswith(f"{sum(counts.values())} messages on ")


@pytest.mark.parametrize(
    ("missing", "named"),
    [(["foxglove"], "foxglove-sdk"), (["foxglove", "matplotlib"], "foxglove-sdk, matplotlib")],
    ids=["foxglove-sdk", "and matplotlib"],  # the probed distribution is drawn with matplotlib
)
def test_gcdtrav_view_without_the_extra_says_what_to_install(missing: list[str], named: str) -> None:
    blocked = "".join(f"sys.modules['{module}'] = None; " for module in missing)
    code = f"import sys; {blocked}from gcdtrav.service.commands.cli import main; sys.exit(main(['view']))"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    expected = f"gcdtrav view: needs {named}; install the view extra: pip install 'gcdtrav[view]'"
    assert result.stderr.strip() == expected


def test_gcdtrav_view_layout_writes_a_tab_per_source_of_the_service(service, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    _, port = service
    flags = ["-m", "client", "-e", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"]
    layout = tmp_path / "layout.json"
    empty = subprocess.run(torch_free_gcdtrav("view", "--layout", str(layout), *flags), capture_output=True,
                           text=True, timeout=60)  # fmt: skip
    assert empty.returncode == 1 and "no sources yet" in empty.stderr and not layout.exists()
    with TraversabilityClient(config=connecting_config(port), timeout=5.0) as client:
        inputs_known(client)
        drive(client, 0)
        assert wait_until(lambda: frame_counted(client, "cam"), 30), "the service's status has no source cam"
    done = subprocess.run(torch_free_gcdtrav("view", "--layout", str(layout), *flags), capture_output=True,
                          text=True, timeout=60)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == f"gcdtrav view: layout for cam written to {layout}"
    document = json.loads(layout.read_text())
    tabs = document["configById"][document["layout"]]["tabs"]
    assert [tab["title"] for tab in tabs] == ["cam"]
