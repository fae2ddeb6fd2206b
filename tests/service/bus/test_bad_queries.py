"""Every query gets an answer: bad documents, strict selectors, and handlers that raise (issue: bad input)."""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import camera_grid, textured_image
from gcdtrav.schemas.anchors import AnchorSet, AnchorSetError
from gcdtrav.schemas.messages import AnchorSetRejection, ErrorReply, MessageError, Pose2D
from gcdtrav.service.runtime.errors import QueryError
from gcdtrav.service.runtime.queries import PATCH_FORMS, parameter_pairs, strict_parameters
from zenoh_helpers import connecting_config, first_frame_through, service_reachable, subscribed_elsewhere, wait_until

TWO = [{"concept": "puddle", "position": 0.0}, {"concept": "road", "position": 1.0}]


@pytest.mark.parametrize(
    "document",
    [
        '{"anchors": ' + "[" * 10_000 + "]" * 10_000 + "}",  # the reported input
        "name: don't\nanchors: " + "[" * 10_000 + "]" * 10_000,  # an apostrophe once hid this from a bracket scan
        "anchors:\n" + "".join("  " * i + "-\n" for i in range(2_000)),  # block style nests by indentation
        "".join("  " * i + "a:\n" for i in range(2_000)),
    ],
    ids=["flow", "after-apostrophe", "block-sequences", "block-mappings"],
)
def test_any_deep_nesting_is_refused_before_the_document_is_built(document: str) -> None:
    with pytest.raises(AnchorSetError, match="nested more than 32 levels deep; an anchor set is 3 levels deep"):
        AnchorSet.from_text(document)


def test_brackets_in_strings_and_comments_are_not_nesting() -> None:
    quoted = '{"name": "[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[", "anchors": ' + json.dumps(TWO) + "}"
    assert AnchorSet.from_text(quoted).name.startswith("[[[")
    commented = (
        "# "
        + "[" * 100
        + "\nname: don't\nanchors:\n"
        + "".join(f"  - {{concept: {a['concept']}, position: {a['position']}}}\n" for a in TWO)
    )
    assert AnchorSet.from_text(commented).name == "don't"


def test_an_integer_beyond_pythons_digit_limit_is_an_invalid_document() -> None:
    with pytest.raises(AnchorSetError, match="not a usable JSON or YAML value: Exceeds the limit"):
        AnchorSet.from_text('{"anchors": [{"concept": "a", "position": ' + "9" * 5000 + "}]}")


def test_deep_documents_are_refused_before_parsing_and_normal_yaml_still_parses() -> None:
    with pytest.raises(AnchorSetError, match="nested more than 32 levels deep"):
        AnchorSet.from_text(b'{"anchors": ' + b"[" * 10_000 + b"]" * 10_000 + b"}")
    yaml_text = "name: puddles\nanchors:\n  - {concept: puddle, position: 0.0}\n  - concept: road\n    position: 1\n"
    assert AnchorSet.from_text(yaml_text).name == "puddles"
    with pytest.raises(AnchorSetError, match="not UTF-8"):
        AnchorSet.from_text(b"\xff\xfe anchors")


def test_free_text_fields_are_bounded_with_the_limit_in_the_message() -> None:
    with pytest.raises(AnchorSetError, match="name: String should have at most 200 characters"):
        AnchorSet.parse({"name": "x" * 100_000, "anchors": TWO})
    with pytest.raises(AnchorSetError, match="concept: String should have at most 1000 characters"):
        AnchorSet.parse({"anchors": [{"concept": "mud " * 2000, "position": 0.0}, TWO[1]]})


def test_selectors_are_strict() -> None:
    assert strict_parameters([("x", "1"), ("y", "2")], PATCH_FORMS) == {"x": "1", "y": "2"}
    with pytest.raises(QueryError, match=re.escape("parameter 'x' is given more than once; give each once: x=..;y=..")):
        strict_parameters(parameter_pairs("x=1;x=2;y=1"), PATCH_FORMS)
    with pytest.raises(QueryError, match="parameter 'x' is given more than once"):
        strict_parameters(parameter_pairs(";".join(["x=1"] * 5000)), PATCH_FORMS)
    with pytest.raises(QueryError, match=re.escape("parameter 'y' has no value; give x=..;y=..")):
        strict_parameters(parameter_pairs("x=1;y="), PATCH_FORMS)
    with pytest.raises(QueryError, match="parameter 'seq' has no value"):
        strict_parameters(parameter_pairs("x=1;y=2;seq"), PATCH_FORMS)


def test_ros_frame_ids_are_bounded() -> None:
    pytest.importorskip("rosbags")
    import numpy as np
    from gcdtrav.service.ros import cdr as ros
    from gcdtrav.service.ros.cdr import decode_pose

    types = ros.typestore().types
    header = ros.make_header(1.0, "f" * 5_000_000)  # fits in a 20 MB payload; was passed on to every output
    image = types[ros.IMAGE](header=header, height=2, width=2, encoding="rgb8", is_bigendian=0, step=6,
                             data=np.zeros(12, np.uint8))  # fmt: skip
    with pytest.raises(ros.RejectedInput, match="frame_id of 5000000 characters is over the limit of 256") as err:
        ros.decode_ros_image(bytes(ros.typestore().serialize_cdr(image, ros.IMAGE)), ros.IMAGE, 100)
    assert err.value.reason == "frame_id_too_long"
    point, quaternion = types["geometry_msgs/msg/Point"], types["geometry_msgs/msg/Quaternion"]
    vector = types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    message = types["nav_msgs/msg/Odometry"](
        header=header, child_frame_id="base_link",
        pose=types["geometry_msgs/msg/PoseWithCovariance"](
            pose=types["geometry_msgs/msg/Pose"](position=point(x=1.0, y=2.0, z=0.0),
                                                 orientation=quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
            covariance=np.zeros(36)),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](
            twist=types["geometry_msgs/msg/Twist"](linear=vector, angular=vector), covariance=np.zeros(36)),
    )  # fmt: skip
    with pytest.raises(MessageError, match="frame_id: String should have at most 256 characters"):
        decode_pose(bytes(ros.typestore().serialize_cdr(message, "nav_msgs/msg/Odometry")), "odometry")


pytest.importorskip("torch")

from gcdtrav.client import AnchorSetRejected, TraversabilityClient  # noqa: E402
from gcdtrav.schemas.settings import ServiceSettings  # noqa: E402
from gcdtrav.service.bus import queryables  # noqa: E402
from gcdtrav.service.bus.node import TraversabilityService  # noqa: E402

from tools.loopback import in_process_service  # noqa: E402


@pytest.fixture()
def served(tiny_backend, tmp_path: Path) -> Iterator[tuple[TraversabilityService, TraversabilityClient]]:  # type: ignore[no-untyped-def]
    settings = ServiceSettings.model_validate(
        {
            "state_dir": str(tmp_path),
            "instance": "strict",
            "preview": False,
            "grids": [camera_grid(camera_info_key="robot/camera_info")],
        }
    )
    with in_process_service(tiny_backend, settings) as (service, port):
        client = TraversabilityClient(config=connecting_config(port), timeout=5.0)
        try:
            # The grid fuses a frame at the robot's pose at its capture stamp: the pose first, then the frame; the
            # pose once the service's subscription is known to the client (put at once before, it could be lost).
            assert wait_until(lambda: service_reachable(client), 60), "the service did not answer"
            assert subscribed_elsewhere(client.session, "robot/pose"), "the pose subscription"
            client.session.put("robot/pose", Pose2D(stamp=0.5, frame_id="odom", x=0.0, y=0.0, yaw=0.0).pack())
            first_frame_through(client, "cam", textured_image(60, 80), stamp=0.5)
            # The maps go out before the frame is counted (and before its grid): wait for the count too.
            assert wait_until(lambda: "cam" in client.status().sources and client.status().sources["cam"].processed, 60)
            yield service, client
        finally:
            client.close()


def raw_get(client: TraversabilityClient, selector: str, payload: bytes | None = None) -> tuple[bool, str]:
    """One reply to a hand-written selector: (ok, the error text or the reply's type)."""
    replies = list(client.session.get(selector, payload=payload, timeout=5.0))
    assert replies, f"no reply to {selector[:80]}"
    reply = replies[0]
    if reply.ok is not None:
        return True, "ok"
    payload = reply.err.payload.to_bytes()
    try:
        return False, ErrorReply.unpack(payload).error
    except MessageError:  # an anchor set's rejection lists every problem
        return False, "; ".join(AnchorSetRejection.unpack(payload).errors)


def test_the_three_reported_inputs_get_clear_replies(served) -> None:  # type: ignore[no-untyped-def]
    service, client = served
    active = service.pipeline.anchors.version
    with pytest.raises(AnchorSetRejected, match="nested more than 32 levels deep"):
        client.set_anchors('{"anchors": ' + "[" * 10_000 + "]" * 10_000 + "}")
    with pytest.raises(AnchorSetRejected, match="body of 100103 bytes is over the limit of 65536 bytes"):
        client.set_anchors({"name": "x" * 100_000, "anchors": TWO})  # the reported input: too big to parse
    with pytest.raises(AnchorSetRejected, match="name: String should have at most 200 characters"):
        client.set_anchors({"name": "x" * 60_000, "anchors": TWO})
    with pytest.raises(AnchorSetRejected, match="over the limit of 65536 bytes"):
        client.set_anchors(" " * 70_000 + '{"anchors": []}')
    assert raw_get(client, "gcdtrav/out/cam/patch?x=1;x=2;y=1") == (
        False,
        f"parameter 'x' is given more than once; give each once: {PATCH_FORMS}",
    )
    ok, error = raw_get(client, "gcdtrav/out/cam/patch?" + ";".join(["x=1"] * 5000))
    assert not ok and "parameter 'x' is given more than once" in error
    assert raw_get(client, "gcdtrav/out/cam/patch?x=1;y=") == (False, f"parameter 'y' has no value; give {PATCH_FORMS}")
    ok, error = raw_get(client, "gcdtrav/out/cam/cell?x=1;x=2;y=0")
    assert not ok and error.startswith("parameter 'x' is given more than once; give each once: x=..;y=.. (metres")
    status = client.status()
    assert status.anchor_set_version == active  # the last good state stays
    assert status.rejected_by_reason["invalid_anchor_set"] == 4 and status.rejected_by_reason["bad_query"] == 4
    assert client.patch("cam", 10, 10).seq == 0  # and the service still serves


def test_keys_without_parameters_refuse_them_and_unknown_formats(served) -> None:  # type: ignore[no-untyped-def]
    _, client = served
    only_format = "this key takes only format=json or format=msgpack"
    bad_format = "format=jsn: give format=json or format=msgpack once [msgpack]"
    for key in ("gcdtrav/status", "gcdtrav/config/anchors", "gcdtrav/config/anchors/history"):
        takes = (
            f"give {queryables.SWAP_FORM}" if key.endswith("anchors") else only_format
        )  # a swap's expected=, proposal=
        assert raw_get(client, f"{key}?x=1") == (False, f"unknown parameter(s) ['x']; {takes}")
        assert raw_get(client, f"{key}?format=jsn") == (False, bad_format)
        assert raw_get(client, f"{key}?format=json")[0]
    assert raw_get(client, "gcdtrav/config/anchors?seq=1", b'{"anchors": []}')[1].startswith("unknown parameter(s)")
    assert client.status().rejected_by_reason["bad_query"] == 7


def test_bad_poses_and_intrinsics_are_rejected_and_the_grid_keeps_the_last_good_ones(served) -> None:  # type: ignore[no-untyped-def]
    import math

    import msgpack
    import numpy as np
    from gcdtrav.client import Grid
    from gcdtrav.service.ros import cdr as ros

    service, client = served
    grids: list[Grid] = []
    subscriber = client.subscribe_grid("cam", grids.append)
    assert subscribed_elsewhere(service.session, service.keys.grid("cam")), "the grid subscription"
    good = {"stamp": 1.0, "frame_id": "odom", "x": 2.0, "y": 0.0, "yaw": 0.0}
    client.session.put("robot/pose", msgpack.packb(good))
    bad_poses = [good | {"x": math.nan}, good | {"y": math.inf}, good | {"x": 1e300}, good | {"frame_id": "f" * 300}]
    for pose in bad_poses:
        client.session.put("robot/pose", msgpack.packb(pose))
    types = ros.typestore().types
    roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    info = types["sensor_msgs/msg/CameraInfo"](
        header=ros.make_header(1.0, "cam"), height=60, width=80, distortion_model="plumb_bob", d=np.zeros(5),
        k=np.array([math.nan, 0, 40, 0, 60.0, 30, 0, 0, 1]), r=np.eye(3).ravel(), p=np.zeros(12),
        binning_x=0, binning_y=0, roi=roi,
    )  # fmt: skip
    client.session.put("robot/camera_info", bytes(ros.typestore().serialize_cdr(info, "sensor_msgs/msg/CameraInfo")))
    rejected = lambda: client.status().rejected_by_reason  # noqa: E731
    assert wait_until(lambda: rejected().get("bad_pose") == 4 and rejected().get("bad_camera_info") == 1, 60)
    errors = " ".join(client.status().last_errors)
    assert "x: Value error, nan is not a finite number" in errors and "1e+300 m is beyond the limit" in errors
    assert "frame_id: String should have at most 256 characters" in errors and "finite intrinsics" in errors
    client.publish_image("cam", textured_image(60, 80, seed=3), stamp=1.0)  # taken at the good pose (moved 2 m)
    assert wait_until(lambda: bool(grids), 60), "no grid after the bad inputs"
    subscriber.undeclare()
    assert grids[-1].header.robot == (2.0, 0.0, 0.0) and grids[-1].header.known_cells > 0  # the last good pose
    assert "processing_failed" not in rejected()
    assert (
        service.runtime.grids is not None and service.runtime.grids.sources["cam"].cameras["cam"].camera.fx == 60
    )  # the configured intrinsics


def boom(*args: object, **kwargs: object) -> None:
    raise RuntimeError("injected fault")


@pytest.mark.parametrize(
    ("queryable", "target", "selector", "payload"),
    [
        ("patch", (queryables, "answer_patch_query"), "gcdtrav/out/cam/patch?x=1;y=1", None),
        ("cell", ("grids", "answer"), "gcdtrav/out/cam/cell?x=2;y=0", None),
        ("anchors", ("switch", "submit"), "gcdtrav/config/anchors", b'{"anchors": []}'),
        ("status", ("service", "status"), "gcdtrav/status", None),
        ("history", ("switch", "history"), "gcdtrav/config/anchors/history", None),
        ("rollback", ("switch", "submit_rollback"), "gcdtrav/config/anchors/rollback?steps=1", None),
    ],
)
def test_a_handler_that_raises_still_answers_and_the_service_goes_on(  # type: ignore[no-untyped-def]
    served, monkeypatch: pytest.MonkeyPatch, queryable: str, target: tuple[object, str], selector: str, payload
) -> None:
    service, client = served
    owner, name = target
    runtime = service.runtime
    owner = {"grids": runtime.grids, "service": service, "switch": runtime.anchor_switch}.get(owner, owner)  # type: ignore[call-overload]
    with monkeypatch.context() as patch:
        patch.setattr(owner, name, boom)
        assert raw_get(client, selector, payload) == (False, "internal error: RuntimeError; see the service log")
    assert raw_get(client, selector, payload)[1] != "internal error: RuntimeError; see the service log"
    status = client.status()
    assert status.rejected_by_reason["query_failed"] == 1, queryable
    assert any("query_failed" in line and "injected fault" in line for line in status.last_errors)
    assert client.patch("cam", 10, 10).seq == 0


def json_get(client: TraversabilityClient, selector: str, payload: bytes | None = None) -> tuple[bool, dict, str]:
    """One reply to ``selector`` as zenoh's own tools see it: (ok, the parsed JSON, its encoding)."""
    import json

    (reply,) = list(client.session.get(selector, payload=payload, timeout=5.0))
    sample = reply.ok if reply.ok is not None else reply.err
    return reply.ok is not None, json.loads(sample.payload.to_bytes()), str(sample.encoding)


def test_every_queryable_answers_json_when_asked(served) -> None:  # type: ignore[no-untyped-def]
    service, client = served
    ok, status, encoding = json_get(client, "gcdtrav/status?format=json")
    assert ok and encoding == "application/json"
    assert status["instance"] == "strict" and status["sources"]["cam"]["processed"] == 1
    assert status["anchor_set_version"] == service.pipeline.anchors.version and status["method"] == "gcd"
    assert status["precision"] == service.pipeline.backend.precision
    assert status["max_sources"] == 256 and status["history_bytes"] > 0
    ok, anchors, _ = json_get(client, "gcdtrav/config/anchors?format=json")
    assert ok and anchors["version"] == service.pipeline.anchors.version
    assert [a["concept"] for a in anchors["anchor_set"]["anchors"]] == service.pipeline.anchors.concepts
    ok, patch, _ = json_get(client, "gcdtrav/out/cam/patch?x=10;y=10;format=json")
    expected = client.patch("cam", 10, 10)  # the same answer in msgpack, through the client
    assert ok and patch["seq"] == 0 and patch["source"] == "cam" and patch["patch"] == list(expected.patch)
    assert patch["mean"] == pytest.approx(expected.mean) and patch["std"] == pytest.approx(expected.std)
    assert sum(patch["weights"]) == pytest.approx(1.0, abs=1e-5) and len(patch["density"]) == len(patch["density_x"])
    cell = client.path("cam", [(0.0, 0.0), (6.0, 0.0)]).cells[0].cell_xy
    ok, cell_json, _ = json_get(client, f"gcdtrav/out/cam/cell?x={cell[0]};y={cell[1]};format=json")
    assert ok and cell_json["cell_xy"] == list(cell) and cell_json["observations"] > 0
    ok, path, _ = json_get(client, "gcdtrav/out/cam/cell?path=0,0;6,0;format=json")
    assert ok and path["points"] == [[0.0, 0.0], [6.0, 0.0]] and path["cells"] and path["lowest_t"] is not None
    # Errors and rejections are JSON too.
    ok, error, encoding = json_get(client, "gcdtrav/out/cam/patch?x=1;x=2;y=1;format=json")
    assert not ok and encoding == "application/json" and error["error"].startswith("parameter 'x' is given more")
    ok, rejection, _ = json_get(client, "gcdtrav/config/anchors?format=json", b'{"anchors": []}')
    assert not ok and rejection["active_version"] == service.pipeline.anchors.version and rejection["errors"]
    # An unknown format: the reply is msgpack (the default) and says which formats there are.
    assert raw_get(client, "gcdtrav/out/cam/patch?x=1;y=1;format=xml") == (
        False,
        "format=xml: give format=json or format=msgpack once [msgpack]",
    )


def test_a_swap_that_fails_on_the_worker_is_rejected_and_the_active_set_stays(served, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    service, client = served
    active = service.pipeline.anchors.version
    monkeypatch.setattr(service.pipeline, "prepare", boom)
    with pytest.raises(AnchorSetRejected, match="swap failed: RuntimeError: injected fault"):
        client.set_anchors({"anchors": TWO})
    assert service.pipeline.anchors.version == active and client.status().rejected_by_reason["swap_failed"] == 1
    assert [e.version for e in client.anchor_history()[0].entries] == [active]  # nothing half-applied
