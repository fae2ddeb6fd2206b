"""What an operator's viewer gets from `gcdtrav view` (issue 35), with a stand-in service (view_fakes): the
grid's risk layers, the robot and its camera placed in 3D, the probed distribution (by parameter and by a point
the 3D panel publishes), questions and log lines replayed to a late viewer, a refused edit answered with the
active value, and a layout with one tab per source naming only topics the viewer advertises."""

from __future__ import annotations

import asyncio
import base64
import json
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import msgpack
import numpy as np
import pytest

pytest.importorskip("foxglove", reason="the view extra: pip install 'gcdtrav[view]'")
pytest.importorskip("websockets")
pytest.importorskip("google.protobuf")
pytest.importorskip("matplotlib")
pytest.importorskip("rosbags")

from foxglove_ws import FoxgloveClient, protobuf_fields
from gcdtrav.client.view.layout import layout, service_sources
from gcdtrav.client.view.replay import question_json
from gcdtrav.client.view.viewer import Viewer, ViewOptions
from gcdtrav.schemas.experience import OperatorAnswer, OperatorQuestion, QuestionConcept
from gcdtrav.schemas.keys import INPUT_MESSAGE_KINDS
from gcdtrav.schemas.messages import GridHeader
from gcdtrav.service.ros.cdr import occupancy_values_cdr
from protobuf_decode import decode
from test_view_recording_cap import camera_payload
from test_view_schemas import lichtblick_datatypes
from view_fakes import PAPER, FakeClient, grid_payload, maps_payload
from zenoh_helpers import wait_until

SETTINGS = """
grids:
  - source: cam
    intrinsics: {fx: 100, fy: 100, cx: 80, cy: 60, width: 160, height: 120}
    mount: {x: 0.2, z: 1.0, pitch: 0.4}
    pose_key: robot/pose
"""
ROBOT = (1.0, 2.0, 0.5)
TOPIC = "/gcdtrav/cam"
LAYER_TOPICS = [f"{TOPIC}/grid/{name}" for name in ("traversability", "uncertainty", "cvar", "p_below", "match",
                                                    "age", "costmap")]  # fmt: skip
PLACED = [f"{TOPIC}/tf", f"{TOPIC}/robot", f"{TOPIC}/camera_info"]


def costmap_payload() -> bytes:
    header = GridHeader.model_validate(msgpack.unpackb(grid_payload("cam"), raw=False)["header"])
    costs = np.array([[-1, 1, 50, 98], [100, 100, 3, -1], [7, 7, 7, 7], [1, 1, 2, 3]], np.int8)
    return occupancy_values_cdr(header, costs)


def question(identifier: str) -> bytes:
    """An OperatorQuestion as the service asks it (with a JPEG crop: bytes travel as base64 in JSON)."""
    return OperatorQuestion(
        id=identifier, source="cam", stamp=100.0, reason="ambiguous", region=(0.0, 0.0, 1.0, 1.0),
        cells=[(0.25, 0.25)], concepts=[QuestionConcept(concept="mud", position=0.3, weight=0.5)],
        anchor_set_version=PAPER.version, crop_jpeg=b"\xff\xd8jpeg",
    ).pack()  # fmt: skip


def feed(viewer: Viewer, client: FakeClient) -> None:
    """One round of everything of source 'cam': maps, a camera frame, the grid with its layers and robot, the
    costmap (the viewer shows each once it arrives)."""
    put, before = client.session.put, viewer.shown["costmap"]
    put("gcdtrav/out/cam/maps", maps_payload("cam", (4, 4), (160, 120)))
    put("gcdtrav/in/cam", camera_payload(1))
    put("gcdtrav/out/cam/grid", grid_payload("cam", robot=ROBOT, layers=True))
    assert wait_until(lambda: viewer.shown["grid"] > before, 30)
    put("gcdtrav/out/cam/grid/costmap", costmap_payload())
    assert wait_until(lambda: viewer.shown["costmap"] > before, 30)


@pytest.fixture()
def fed(tmp_path: Path) -> Iterator[tuple[Viewer, FakeClient]]:
    """A viewer that has seen everything of source 'cam' and a question, and said something in its log
    (about a bad question), before any browser connects."""
    settings = tmp_path / "gcdtrav.yaml"
    settings.write_text(SETTINGS)
    client = FakeClient()
    viewer = Viewer(client, ViewOptions(port=0, status_period_s=0.2, settings=settings)).start()  # type: ignore[arg-type]
    try:
        feed(viewer, client)
        put = client.session.put
        put("gcdtrav/out/cam/question", msgpack.packb({"id": "q1", "text": "is this mud?", "patch": [1, 2]}))
        put("gcdtrav/out/cam/question", b"not a question")
        put("gcdtrav/out/cam/question", question("q0"))
        put("gcdtrav/in/cam/answer", OperatorAnswer(id="q0", source="cam", score=1.0).pack())  # no longer open
        yield viewer, client
    finally:
        viewer.close()


async def late_viewer(
    url: str, topics: list[str], replayed: list[str], then: Any = None, until: list[str] | None = None
) -> FoxgloveClient:
    """Connect, subscribe to ``topics``, wait for the ``replayed`` ones (sent before it connected), then run
    ``then`` (e.g. new data) and wait for ``until``."""
    fox = await FoxgloveClient.connect(url)
    await fox.until(lambda: all(topic in fox.channels for topic in topics))
    await fox.subscribe(*topics)
    await fox.until(lambda: all(fox.received(topic) for topic in replayed))
    fox.replayed = {topic: list(fox.received(topic)) for topic in replayed}  # type: ignore[attr-defined]
    if then is not None:
        await asyncio.to_thread(then)
    await fox.until(lambda: all(fox.received(topic) for topic in until or []))
    await fox.close()
    return fox


def decoded(fox: FoxgloveClient, topic: str) -> dict[str, Any]:
    """The topic's last message, decoded with the schema its channel advertised (as Lichtblick reads it)."""
    channel = fox.channels[topic]
    if channel["encoding"] == "json":
        lichtblick_datatypes(json.loads(channel["schema"]), channel["schemaName"])
        return dict(json.loads(fox.received(topic)[-1]))
    assert channel["schemaEncoding"] == "protobuf" and channel["schemaName"].startswith("foxglove.")
    return decode(channel["schemaName"], base64.b64decode(channel["schema"]), fox.received(topic)[-1])


def test_a_late_viewer_gets_risk_layers_the_robot_its_camera_questions_and_the_log(fed: tuple[Viewer, Any]) -> None:
    viewer, client = fed
    assert viewer.shown["grid"] == 1 and viewer.logged[f"{TOPIC}/grid/cvar"] == 0  # nobody watching: not drawn
    images = [f"{topic}/image" for topic in LAYER_TOPICS]
    replayed = [f"{TOPIC}/question", "/gcdtrav/log"]
    topics = [*LAYER_TOPICS, *images, *PLACED, f"{TOPIC}/camera", *replayed]
    fox = asyncio.run(late_viewer(viewer.url, topics, replayed, lambda: feed(viewer, client), topics))

    for topic in LAYER_TOPICS:  # a value and its colour per cell, in the grid's frame
        grid = decoded(fox, topic)
        assert grid["frame_id"] == "odom" and grid["column_count"] == 4 and grid["cell_stride"] == 8
        names = [field["name"] for field in grid["fields"]]
        assert names[1:] == ["red", "green", "blue", "alpha"] and topic.endswith(names[0])
    cvar = decoded(fox, f"{TOPIC}/grid/cvar")
    cells = np.frombuffer(base64.b64decode(cvar["data"]), np.dtype([("v", "<f4"), ("a", "u1", (4,))]))
    assert np.isnan(cells["v"][0]) and np.allclose(cells["v"][1:], 0.25, atol=1e-4)
    costmap = decoded(fox, f"{TOPIC}/grid/costmap")
    costs = np.frombuffer(base64.b64decode(costmap["data"]), np.dtype([("v", "<f4"), ("a", "u1", (4,))]))
    assert np.isnan(costs["v"][0]) and costs["v"][4] == 100 and costs["a"][0][3] == 0
    for topic in images:  # a picture with a legend
        picture = decoded(fox, topic)
        pixels = cv2.imdecode(np.frombuffer(base64.b64decode(picture["data"]), np.uint8), 1)
        assert picture["format"] == "png" and picture["frame_id"] == "odom" and pixels.shape[0] >= 256

    transforms = decoded(fox, f"{TOPIC}/tf")["transforms"]  # the last: odom -> base_link
    assert (transforms[0]["parent_frame_id"], transforms[0]["child_frame_id"]) == ("odom", "base_link")
    assert transforms[0]["translation"] == {"x": 1.0, "y": 2.0, "z": 0.0}
    mounts = [decode_tf(fox, raw) for raw in fox.received(f"{TOPIC}/tf")]
    assert ("base_link", "front") in {pair for message in mounts for pair in message}  # base_link -> camera
    scene = decoded(fox, f"{TOPIC}/robot")["entities"]
    assert {entity["frame_id"] for entity in scene} == {"front", "base_link"}  # frustum, robot
    calibration = decoded(fox, f"{TOPIC}/camera_info")
    assert calibration["frame_id"] == "front" and calibration["width"] == 160
    assert decoded(fox, f"{TOPIC}/camera")["frame_id"] == "front"  # images in the camera's frame

    replays = fox.replayed  # type: ignore[attr-defined]
    open_questions = [json.loads(raw) for raw in replays[f"{TOPIC}/question"]]  # they came before this viewer
    assert open_questions == [{"id": "q1", "text": "is this mud?", "patch": [1, 2]}]  # q0 was answered
    assert viewer.errors["question"] == 1 and viewer.errors["camera"] == 0  # the answer is not a camera frame
    assert set(viewer._sources) == {"cam"}
    as_json = question_json(question("q2"))  # a real OperatorQuestion: its JPEG crop as base64 text
    assert as_json["id"] == "q2" and as_json["crop_jpeg"] == base64.b64encode(b"\xff\xd8jpeg").decode()
    assert json.loads(json.dumps(as_json)) == as_json
    lichtblick_datatypes(json.loads(fox.channels[f"{TOPIC}/question"]["schema"]), "gcdtrav.OperatorQuestion")
    lines = [decode_log(fox, raw) for raw in replays["/gcdtrav/log"]]
    assert any("question of cam not shown" in line for line in lines)  # said before it connected


def decode_tf(fox: FoxgloveClient, raw: bytes) -> list[tuple[str, str]]:
    channel = fox.channels[f"{TOPIC}/tf"]
    message = decode(channel["schemaName"], base64.b64decode(channel["schema"]), raw)
    return [(t["parent_frame_id"], t["child_frame_id"]) for t in message["transforms"]]


def decode_log(fox: FoxgloveClient, raw: bytes) -> str:
    channel = fox.channels["/gcdtrav/log"]
    return str(decode(channel["schemaName"], base64.b64decode(channel["schema"]), raw)["message"])


async def probe_by_parameter_and_by_point(url: str, client: FakeClient) -> dict[str, Any]:
    fox = await FoxgloveClient.connect(url)
    await fox.until(lambda: f"{TOPIC}/grid" in fox.channels)
    # as Lichtblick's Parameters panel: updates of the names it lists
    await fox.send(op="subscribeParameterUpdates", parameterNames=["probe/target", "anchors/02/position"])
    changes = [{"name": "probe/source", "value": "cam"}, {"name": "probe/x", "value": 40.0},
               {"name": "probe/y", "value": 30.0}]  # fmt: skip
    await fox.send(op="setParameters", parameters=changes, id="probe")
    await fox.until(lambda: f"{TOPIC}/distribution" in fox.channels)
    await fox.subscribe(f"{TOPIC}/distribution")  # sent again if refused: the channel is brand new
    await fox.until(lambda: bool(fox.received(f"{TOPIC}/distribution")))
    # a published point, as Lichtblick v1.28.1 advertised and sent it (seen live, from its Publish panel; its 3D
    # panel's "Publish point" builds the same message in the display frame): a client channel, then JSON
    await fox.send(op="advertise", channels=[{"id": 7, "topic": "/clicked_point", "encoding": "json",
                                              "schemaName": "geometry_msgs/PointStamped"}])  # fmt: skip
    point = b'{"header":{"stamp":{"sec":0,"nsec":0},"frame_id":"base_link"},"point":{"x":1,"y":0,"z":0}}'
    await fox.websocket.send(struct.pack("<BI", 1, 7) + point)
    await fox.until(lambda: any(p.get("value") == "cell" for op in fox.ops_named("parameterValues")
                                for p in op["parameters"] if p["name"] == "probe/target"))  # fmt: skip
    # the probe loop queries only while someone watches the distribution: before this viewer leaves
    await fox.until(lambda: any(query[0] == "cell" for query in client.queries))
    # a refused anchor edit, sent as the Parameters panel does: the panel is told the active value again
    before = len(fox.ops_named("parameterValues"))
    await fox.send(op="setParameters", parameters=[{"name": "anchors/02/position", "value": 1.5}])
    await fox.until(lambda: any(p["name"] == "anchors/02/position" and p["value"] == pytest.approx(0.2)
                                for op in fox.ops_named("parameterValues")[before:]
                                for p in op["parameters"]))  # fmt: skip
    await fox.close()
    return {"picture": fox.received(f"{TOPIC}/distribution")[0], "ops": fox.ops_named("parameterValues")}


def test_the_probed_distribution_by_parameter_and_by_a_published_point(fed: tuple[Viewer, FakeClient]) -> None:
    viewer, client = fed
    seen = asyncio.run(probe_by_parameter_and_by_point(viewer.url, client))
    assert ("patch", "cam", 40.0, 30.0) in client.queries
    x, y, yaw = ROBOT  # 1 m ahead of the robot, in odom
    cell = next(query for query in client.queries if query[0] == "cell")
    assert cell[1] == "cam" and cell[2:] == pytest.approx((x + np.cos(yaw), y + np.sin(yaw)))
    fields = protobuf_fields(seen["picture"])
    picture = cv2.imdecode(np.frombuffer(fields[2][0], np.uint8), cv2.IMREAD_COLOR)
    assert fields[3] == [b"png"] and picture.shape[0] > 200 and picture.shape[1] > 400  # the density plot


def test_the_layout_has_a_tab_per_source_and_only_topics_the_viewer_advertises(fed: tuple[Viewer, Any]) -> None:
    viewer, _ = fed
    document = json.loads(json.dumps(layout(["cam", "r1/front"])))  # as written to the file
    configs = document["configById"]
    tabs = configs[document["layout"]]["tabs"]
    assert [tab["title"] for tab in tabs] == ["cam", "r1/front"]

    def panels(mosaic: Any) -> list[str]:
        if isinstance(mosaic, str):
            return [mosaic]
        assert set(mosaic) == {"direction", "first", "second", "splitPercentage"}
        assert mosaic["direction"] in ("row", "column")
        return panels(mosaic["first"]) + panels(mosaic["second"])

    in_tabs = [panel for tab in tabs for panel in panels(tab["layout"])]
    assert len(in_tabs) == len(set(in_tabs)) and set(in_tabs) | {document["layout"]} == set(configs)
    assert all(panel.split("!")[0] in ("Image", "3D", "RosOut", "Parameters", "RawMessages") for panel in in_tabs)

    topics = set()
    for panel in in_tabs:
        config = configs[panel]
        topics.update(config.get("topics", {}))
        topics.update(v for v in (config.get("imageMode", {}).get("imageTopic"),
                                  config.get("imageMode", {}).get("calibrationTopic"),
                                  config.get("topicPath"), config.get("topicToRender")) if v)  # fmt: skip
    cam_topics = {topic for topic in topics if not topic.startswith("/gcdtrav/r1/")}
    viewer.set_probe({"probe/source": "cam"})  # the distribution channel appears with the probe
    fox = asyncio.run(late_viewer(viewer.url, [f"{TOPIC}/distribution"], []))
    missing = cam_topics - set(fox.channels) - {f"{TOPIC}/preview"}
    assert not missing, missing
    assert {t.replace("/gcdtrav/r1/front/", "/gcdtrav/cam/") for t in topics - cam_topics} == cam_topics - {
        "/gcdtrav/log"
    }


def test_layout_sources_are_every_instances_plus_named_grids() -> None:
    status = FakeClient().statuses()[0]
    one = status.model_copy(update={"sources": {"r1/front": status.sources.get("x") or {}}})
    assert service_sources([one], ["r1/all"]) == ["r1/all", "r1/front"]
    assert service_sources([], []) == [] and PAPER.name == "paper"
    with pytest.raises(ValueError, match="at least one source"):
        layout([])


def test_the_experience_s_messages_beside_the_images_are_not_cameras(fed: tuple[Viewer, FakeClient]) -> None:
    """Outcomes, answers and planned paths arrive under {prefix}/in/{source}/ too (schemas/keys.py's
    INPUT_MESSAGE_KINDS): none of them is shown, or counted, as a camera frame."""
    viewer, client = fed
    shown, errors = viewer.shown["camera"], viewer.errors["camera"]
    for kind in INPUT_MESSAGE_KINDS:
        client.session.put(f"gcdtrav/in/cam/{kind}", msgpack.packb({"source": "cam"}))
    client.session.put("gcdtrav/in/cam", camera_payload(2))  # after them: once it is shown, they were judged
    assert wait_until(lambda: viewer.shown["camera"] > shown, 30)
    assert viewer.errors["camera"] == errors
