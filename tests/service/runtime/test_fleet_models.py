"""Who may take sources by the model it runs: the same decision on every instance, from the member tokens."""

from __future__ import annotations

from pathlib import Path

import pytest
from gcdtrav.schemas.settings import SettingsError
from gcdtrav.service.runtime.fleet_models import HELD, MIXED, SERVING, Member, decide, own_state, reference_of
from gcdtrav.service.runtime.state_lock import StateLock


def members(*items: Member) -> dict[str, Member]:
    return {m.instance: m for m in items}


def test_a_newcomer_with_another_model_is_refused_by_every_instance() -> None:
    fleet = members(Member("a", "x1", SERVING, 100), Member("b", "y2", HELD, 50))  # b's clock runs behind
    view = decide({"a", "b"}, fleet)
    assert set(view.refused) == {"b"} and "differs from the fleet's x1" in view.refused["b"]
    assert view.eligible({"a", "b"}) == {"a"}
    assert own_state("b", view, allow_mixed=False) == HELD and own_state("a", view, allow_mixed=False) == SERVING


def test_two_instances_started_at_once_are_ordered_by_their_stamps_then_names() -> None:
    both_held = members(Member("b", "y2", HELD, 100), Member("a", "x1", HELD, 100))
    assert set(decide({"a", "b"}, both_held).refused) == {"b"}  # same ms: by name
    assert set(decide({"a", "b"}, members(Member("a", "x1", HELD, 101), Member("b", "y2", HELD, 100))).refused) == {"a"}


def test_newcomers_never_take_the_fleet_by_numbers_and_a_refused_model_resumes_when_the_fleet_leaves() -> None:
    fleet = members(Member("a", "x1", SERVING, 100), *(Member(f"n{i}", "y2", HELD, 200 + i) for i in range(3)))
    assert set(decide(set(fleet), fleet).refused) == {"n0", "n1", "n2"}
    without_a = {name for name in fleet if name != "a"}
    assert decide(without_a, fleet).refused == {}  # the reference is the earliest held one now


def test_mixed_instances_share_and_define_the_model_once_the_old_ones_are_gone() -> None:
    fleet = members(Member("a", "x1", SERVING, 100), Member("c", "y2", MIXED, 200), Member("d", "y2", HELD, 300))
    assert set(decide({"a", "c", "d"}, fleet).refused) == {"d"}  # c shares, strict d waits
    assert decide({"c", "d"}, fleet).refused == {}  # upgrade done: the fleet's model is y2
    assert own_state("c", decide({"a", "c"}, fleet), allow_mixed=True) == MIXED


def test_an_instance_without_a_member_token_suspends_the_rule_and_no_fingerprint_is_never_refused() -> None:
    fleet = members(Member("a", "x1", SERVING, 100), Member("b", "y2", HELD, 200))
    view = decide({"a", "b", "old"}, fleet)  # "old" only has an alive token: it counts everyone
    assert view.refused == {} and "old advertises no model" in view.suspended
    unknown = members(Member("a", "x1", SERVING, 100), Member("u", "", SERVING, 50))
    assert decide({"a", "u"}, unknown).refused == {}
    assert reference_of(unknown.values()) == unknown["a"]


def test_a_state_file_takes_one_service_and_is_free_again_once_released(tmp_path: Path) -> None:
    state = tmp_path / "gcdtrav.anchors.json"
    first = StateLock(state, "box-a")
    with pytest.raises(SettingsError, match=r"in use by instance box-a \(pid \d+\).*own --state-dir"):
        StateLock(state, "box-b")
    first.release()
    StateLock(state, "box-b").release()
