from __future__ import annotations

import json
from pathlib import Path

import pytest
from gcdtrav.schemas.anchors import Anchor, AnchorSet, AnchorSetError, default_anchor_set


def make(anchors: list[dict], **extra: object) -> dict:
    return {"anchors": anchors, **extra}


def errors_of(data: object) -> list[str]:
    with pytest.raises(AnchorSetError) as info:
        AnchorSet.parse(data)
    return info.value.messages


def test_default_is_the_papers_set() -> None:
    cas = default_anchor_set()
    assert cas.concepts[0] == "water" and cas.positions[0] == 0.02
    assert cas.concepts[-1] == "concrete" and cas.positions[-1] == 1.0
    assert len(cas) == 13
    assert cas.widths == [0.0] * 13


def test_position_outside_unit_interval_is_named() -> None:
    messages = errors_of(make([{"concept": "a", "position": 0.1}, {"concept": "b", "position": 1.5}]))
    assert any("anchors.1.position" in m and "outside [0, 1]" in m for m in messages)


def test_order_must_be_non_decreasing() -> None:
    messages = errors_of(make([{"concept": "grass", "position": 0.5}, {"concept": "water", "position": 0.02}]))
    assert any("sorted by position" in m and "'water'" in m for m in messages)


def test_equal_positions_are_allowed() -> None:
    cas = AnchorSet.parse(make([{"concept": "a", "position": 0.5}, {"concept": "b", "position": 0.5}]))
    assert cas.positions == [0.5, 0.5]


def test_duplicate_and_empty_concepts() -> None:
    dup = errors_of(make([{"concept": "Mud", "position": 0.1}, {"concept": "mud", "position": 0.2}]))
    assert any("more than once" in m for m in dup)
    empty = errors_of(make([{"concept": "  ", "position": 0.1}, {"concept": "mud", "position": 0.2}]))
    assert any("non-empty" in m for m in empty)


@pytest.mark.parametrize("count", [1, 65])
def test_anchor_count_limits(count: int) -> None:
    anchors = [{"concept": f"c{i}", "position": i / 100} for i in range(count)]
    messages = errors_of(make(anchors))
    assert any("between 2 and 64" in m for m in messages)


def test_sixty_four_anchors_accepted() -> None:
    cas = AnchorSet.parse(make([{"concept": f"terrain {i}", "position": i / 63} for i in range(64)]))
    assert len(cas) == 64


def test_concept_longer_than_clip_context_rejected() -> None:
    long_text = " ".join(["gravel"] * 76)
    messages = errors_of(make([{"concept": long_text, "position": 0.1}, {"concept": "mud", "position": 0.2}]))
    assert any("CLIP tokens" in m for m in messages)
    ok_text = " ".join(["gravel"] * 75)
    assert AnchorSet.parse(make([{"concept": ok_text, "position": 0.1}, {"concept": "mud", "position": 0.2}]))


def test_negative_width_and_unknown_fields() -> None:
    messages = errors_of(make([{"concept": "a", "position": 0.1, "width": -0.1}, {"concept": "b", "position": 0.2}]))
    assert any("width" in m and ">= 0" in m for m in messages)
    messages = errors_of(make([{"concept": "a", "position": 0.1, "colour": "red"}, {"concept": "b", "position": 0.2}]))
    assert any("anchors.0.colour" in m and "unknown field" in m for m in messages)
    messages = errors_of(make([{"concept": "a", "position": 0.1}, {"concept": "b", "position": 0.2}], extra=1))
    assert any(m.startswith("extra") for m in messages)


def test_widths_default_and_override() -> None:
    cas = AnchorSet.parse(
        make(
            [{"concept": "a", "position": 0.1}, {"concept": "b", "position": 0.2, "width": 0.05}],
            default_width=0.02,
        )
    )
    assert cas.widths == [0.02, 0.05]


def test_version_is_stable_and_content_based() -> None:
    a = default_anchor_set()
    b = AnchorSet.parse(json.loads(a.to_json()) | {"name": "renamed"})
    assert a.version == b.version  # the name does not change results
    moved = json.loads(a.to_json())
    moved["anchors"][0]["position"] = 0.03
    assert AnchorSet.parse(moved).version != a.version
    widened = json.loads(a.to_json()) | {"default_width": 0.01}
    assert AnchorSet.parse(widened).version != a.version
    assert len(a.version) == 16 and int(a.version, 16) >= 0


@pytest.mark.parametrize("suffix", [".json", ".yaml"])
def test_save_and_load_round_trip(tmp_path: Path, suffix: str) -> None:
    cas = AnchorSet(
        name="mine",
        default_width=0.01,
        anchors=[Anchor(concept="puddle", position=0.0, width=0.05), Anchor(concept="road", position=1.0)],
    )
    path = tmp_path / f"set{suffix}"
    cas.save(path)
    assert AnchorSet.load(path) == cas


def test_load_reports_file_and_problem(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("anchors: [ {concept: a, position: 0.5\n")
    with pytest.raises(AnchorSetError, match=r"bad\.yaml.*not valid JSON or YAML"):
        AnchorSet.load(bad)
    with pytest.raises(AnchorSetError, match="cannot read"):
        AnchorSet.load(tmp_path / "missing.json")
    with pytest.raises(AnchorSetError, match="expected a mapping"):
        AnchorSet.from_text("[1, 2]")


def test_a_duplicate_concept_is_reported_beside_field_errors() -> None:
    """Field errors stop pydantic before the set's own checks; the duplicate went unreported (issue 36)."""
    data = {
        "anchors": [
            {"concept": "grass", "position": 0.5},
            {"concept": "Grass", "position": 0.6, "colour": "green"},  # a field error in the same file
            {"concept": "mud", "position": 1.5},
        ]
    }
    with pytest.raises(AnchorSetError) as rejected:
        AnchorSet.parse(data, "set.yaml")
    messages = rejected.value.messages
    assert any(m.startswith("anchors.1.colour: unknown field") for m in messages)
    assert any(m.startswith("anchors.2.position: position 1.5 is outside [0, 1]") for m in messages)
    assert "concept 'Grass' appears more than once; concepts must be unique" in messages
    assert not any("sorted" in m for m in messages)  # 1.5 has its own error: not also out of order
    only_duplicate = {"anchors": [{"concept": "grass", "position": 0.5}, {"concept": "grass", "position": 0.6}]}
    with pytest.raises(AnchorSetError) as once:
        AnchorSet.parse(only_duplicate)
    assert once.value.messages == ["concept 'grass' appears more than once; concepts must be unique"]  # not twice
