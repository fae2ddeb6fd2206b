"""Every query gets an answer: bad documents, strict selectors, and handlers that raise (issue: bad input)."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import textured_image
from gcdtrav.schemas.anchors import AnchorSet, AnchorSetError
from gcdtrav.schemas.limits import nesting_depth
from gcdtrav.schemas.messages import AnchorSetRejection, ErrorReply, MessageError
from gcdtrav.service.queries import PATCH_FORMS, QueryError, parameter_pairs, strict_parameters
from zenoh_helpers import connecting_config, first_frame_through

TWO = [{"concept": "puddle", "position": 0.0}, {"concept": "road", "position": 1.0}]


def test_nesting_depth_counts_brackets_outside_strings() -> None:
    assert nesting_depth('{"anchors": [{"concept": "a", "position": 0}]}') == 3
    assert nesting_depth('{"name": "[[[{{{", "x": \'[[\'}') == 1
    assert nesting_depth('{"a": "\\"[[["}') == 1
    assert nesting_depth("[" * 10_000 + "]" * 10_000) == 10_000


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


pytest.importorskip("torch")

from gcdtrav.client import AnchorSetRejected, TraversabilityClient  # noqa: E402
from gcdtrav.schemas.settings import ServiceSettings  # noqa: E402
from gcdtrav.service.bus import node as node_module  # noqa: E402
from gcdtrav.service.bus.node import TraversabilityService  # noqa: E402
from gcdtrav.service.loopback import in_process_service  # noqa: E402

GRID = {
    "source": "cam",
    "intrinsics": {"fx": 60, "fy": 60, "cx": 40, "cy": 30, "width": 80, "height": 60},
    "mount": {"z": 1.0, "pitch": 0.6},
    "size_m": 8.0,
    "resolution_m": 0.25,
}


@pytest.fixture()
def served(tiny_backend, tmp_path: Path) -> Iterator[tuple[TraversabilityService, TraversabilityClient]]:  # type: ignore[no-untyped-def]
    settings = ServiceSettings.model_validate(
        {"state_dir": str(tmp_path), "instance": "strict", "preview": False, "grids": [GRID]}
    )
    with in_process_service(tiny_backend, settings) as (service, port):
        client = TraversabilityClient(config=connecting_config(port), timeout=5.0)
        try:
            first_frame_through(client, "cam", textured_image(60, 80))
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


def boom(*args: object, **kwargs: object) -> None:
    raise RuntimeError("injected fault")


@pytest.mark.parametrize(
    ("queryable", "target", "selector", "payload"),
    [
        ("patch", (node_module, "answer_patch_query"), "gcdtrav/out/cam/patch?x=1;y=1", None),
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
    owner = {"grids": service.grids, "service": service, "switch": service.anchor_switch}.get(owner, owner)  # type: ignore[call-overload]
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
