"""The protocol's keys: built and parsed in one place, the same as docs/messages.md lists them."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from gcdtrav.schemas.keys import GRID_LAYERS, OUTPUT_KINDS, Keys, input_key

DOCS = Path(__file__).resolve().parents[2] / "docs" / "messages.md"


def test_every_key_under_a_prefix() -> None:
    keys = Keys("fleet/a")
    assert keys.maps("r1/front") == "fleet/a/out/r1/front/maps"
    assert keys.preview("cam") == "fleet/a/out/cam/preview"
    assert keys.patch("**") == "fleet/a/out/**/patch"
    assert keys.grid("cam") == "fleet/a/out/cam/grid"
    assert keys.grid("cam", "occupancy") == "fleet/a/out/cam/grid/occupancy"
    assert keys.cell("cam") == "fleet/a/out/cam/cell"
    assert keys.anchors == "fleet/a/config/anchors"
    assert keys.anchor_history == "fleet/a/config/anchors/history"
    assert keys.anchor_rollback == "fleet/a/config/anchors/rollback"
    assert keys.status == "fleet/a/status"
    assert keys.alive("box-1") == "fleet/a/alive/box-1" and keys.alive() == "fleet/a/alive/*"
    assert keys.maps8("r1/front") == "fleet/a/out/r1/front/maps8"
    assert keys.credit("r1/front") == "fleet/a/credit/r1/front" and keys.credit("**") == "fleet/a/credit/**"
    assert keys.credit_source_of("fleet/a/credit/r1/front") == "r1/front"
    assert keys.credit_source_of("fleet/a/credit/**") is None and keys.credit_source_of("fleet/a/status") is None
    assert keys.relay_health("r1/front") == "fleet/a/relay/r1/front/health"
    assert keys.relay_parked("r1/front") == "fleet/a/relay/r1/front/parked"
    assert keys.relay_health_source_of(keys.relay_health("r1/front")) == "r1/front"
    assert keys.relay_health_source_of(keys.relay_parked("r1/front")) is None
    assert keys.relay_health_source_of(keys.relay_health("**")) is None
    assert keys.outputs == "fleet/a/out/**"
    assert input_key("gcdtrav/in", "r1/front") == "gcdtrav/in/r1/front"
    with pytest.raises(ValueError, match="unknown output kind 'map'"):
        keys.output("cam", "map")


@pytest.mark.parametrize("source", ["cam", "r1/front", "a/b/c"])
@pytest.mark.parametrize("kind", OUTPUT_KINDS)
def test_source_of_inverts_every_output_key(source: str, kind: str) -> None:
    keys = Keys()
    assert keys.source_of(keys.output(source, kind), kind) == source


def test_source_of_refuses_what_is_not_one_source() -> None:
    keys = Keys()
    assert keys.source_of("gcdtrav/out/**/patch", "patch") is None  # an expression, not a source
    assert keys.source_of("gcdtrav/out//patch", "patch") is None
    assert keys.source_of("gcdtrav/out/cam/maps", "patch") is None
    assert keys.source_of("other/out/cam/patch", "patch") is None
    assert keys.source_of("gcdtrav/out/$*/patch", "patch") is None
    assert keys.instance_of("gcdtrav/alive/box-1") == "box-1" and keys.instance_of("gcdtrav/status") is None
    token = keys.active_anchors("site/box-1", "1700000000123", "0123456789abcdef")
    assert keys.parse_active_anchors(token) == ("site/box-1", 1700000000123, "0123456789abcdef")
    assert keys.parse_active_anchors(keys.alive("box-1")) is None
    assert keys.parse_active_anchors(keys.active_anchors("box-1", "soon", "v")) is None


def test_docs_list_the_same_keys() -> None:
    documented = set(re.findall(r"`(\{prefix\}/[a-z0-9_/{}]+)", DOCS.read_text("utf-8")))
    keys = Keys("{prefix}")
    built = {keys.output("{source}", kind) for kind in OUTPUT_KINDS}
    built |= {keys.grid("{source}", layer) for layer in GRID_LAYERS}
    built |= {keys.anchors, keys.anchor_history, keys.anchor_rollback, keys.status, keys.alive("{instance}")}
    built |= {keys.credit("{source}"), keys.relay_health("{source}"), keys.relay_parked("{source}")}
    built |= {keys.active_anchors("{instance}", "{millis}", "{version}")}
    built |= {keys.outcome("{source}"), keys.answer("{source}"), keys.planned_path("{source}"), keys.anchor_proposal}
    assert built <= documented, f"missing from docs/messages.md: {sorted(built - documented)}"


def test_outcome_and_answer_keys_are_messages_never_image_sources() -> None:
    keys = Keys("site")
    assert keys.input_message(keys.outcome("r1/front")) == ("r1/front", "outcome")
    assert keys.input_message(keys.answer("cam")) == ("cam", "answer")
    assert keys.input_message(keys.planned_path("r1")) == ("r1", "planned_path")
    assert keys.input_message("site/in/r1/front") is None  # an image
    assert keys.input_message("site/in/outcome") is None  # a camera named 'outcome': no source before it
    assert keys.input_message("gcdtrav/in/cam/outcome") is None  # another prefix's
    assert keys.input_message("site/in/**/outcome") is None  # an expression, not a source
