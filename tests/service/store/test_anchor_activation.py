"""The anchor set's record in the fleet's store, through AnchorSwitch, on both backends (SQLite; PostgreSQL in
a throw-away cluster): of two instances swapping at once exactly one wins and the other names the winner;
the start set seeds an empty store only; the active set survives a restart of every instance; rollback and
history read the store, so a new instance rolls back the fleet's history, not its own."""

from __future__ import annotations

import threading
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from conftest import three_anchor_set
from gcdtrav.schemas.anchors import AnchorSet, default_anchor_set
from gcdtrav.schemas.config import EngineSettings
from gcdtrav.schemas.messages import AnchorHistoryEntry, AnchorHistoryReply
from gcdtrav.service.backends.base import BackendDescription
from gcdtrav.service.pipeline import Pipeline
from gcdtrav.service.runtime.fleet.anchor_switch import ActivationLost, AnchorSwitch
from gcdtrav.service.store.legacy import history_file_of, import_anchor_state
from numpy.typing import NDArray
from store_fixtures import OpenStore


class NamesBackend:
    """Embeds nothing: a set's 'embedding' is its concepts (the store, not the model, is under test)."""

    model_id = "names"

    def describe(self) -> BackendDescription:
        return BackendDescription(self.model_id)

    def prepare(self, concepts: Sequence[str]) -> object:
        return tuple(concepts)

    def logits(self, image_rgb: NDArray[np.uint8], prepared: object) -> NDArray[np.float32]:
        return np.zeros((len(prepared), 2, 2), np.float32)  # type: ignore[arg-type]


def instance(
    open_store: OpenStore, name: str, start: AnchorSet | None = None, legacy: Path | None = None
) -> AnchorSwitch:
    """An instance starting on an empty state dir with ``start`` configured (default: the paper's set), its
    anchor state from before the store in ``legacy`` imported as the service's store opening does."""
    pipeline = Pipeline(NamesBackend(), start or default_anchor_set(), EngineSettings())
    store = open_store()
    if legacy is not None:
        import_anchor_state(store, legacy, name)
    return AnchorSwitch(pipeline, store, name, 65536)


def race(
    switches: Sequence[AnchorSwitch], sets: dict[str, AnchorSet], seen: str
) -> dict[str, AnchorSet | ActivationLost]:
    """Each instance swaps to its set at the same moment, expecting ``seen`` active (as two operators would)."""
    barrier = threading.Barrier(len(switches))
    results: dict[str, AnchorSet | ActivationLost] = {}

    def operator(switch: AnchorSwitch) -> None:
        barrier.wait()
        try:
            results[switch.instance] = switch.swap(sets[switch.instance], expected=seen)
        except ActivationLost as lost:
            results[switch.instance] = lost

    threads = [threading.Thread(target=operator, args=(switch,)) for switch in switches]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(20)
    return results


def test_of_two_instances_swapping_at_once_exactly_one_wins_and_the_other_names_it(
    open_same_store: OpenStore,
) -> None:
    a, b = instance(open_same_store, "box-a"), instance(open_same_store, "box-b")
    assert b.head().version == a.head().version  # b found the set a seeded
    for round_ in range(5):  # each round both expect the set they saw
        seen = a.head().version
        sets = {"box-a": three_anchor_set(f"a{round_}"), "box-b": three_anchor_set(f"b{round_}")}
        results = race([a, b], sets, seen)
        won = [name for name, result in results.items() if isinstance(result, AnchorSet)]
        assert len(won) == 1, results
        lost = results[next(name for name in results if name not in won)]
        assert isinstance(lost, ActivationLost) and lost.winner.version == sets[won[0]].version
        assert f"anchor set {sets[won[0]].version} was activated first (by {won[0]})" in str(lost)
        history = a.store.history(50)
        assert history[0].version == sets[won[0]].version and len(history) == round_ + 2  # one entry per round
        loser = b if won == ["box-a"] else a
        loser.swap(sets[won[0]], expected=seen)  # the loser's instance learns it (AnchorSync, over zenoh)
        assert loser.store.history(50)[0].entry == history[0].entry  # installed, not recorded twice
    a.close()
    b.close()


def test_the_start_set_seeds_an_empty_store_only_and_the_active_set_survives_every_restart(
    open_same_store: OpenStore,
) -> None:
    configured = three_anchor_set("configmap")
    first = instance(open_same_store, "box-a", configured)
    seeded = first.store.active()
    assert seeded is not None and seeded.version == configured.version and seeded.how == "seeded"
    applied = three_anchor_set("applied")
    first.swap(applied, expected=configured.version)
    first.close()
    first.store.close()  # every instance stopped
    for name in ("box-b", "box-c"):  # new instances on empty state dirs, the ConfigMap's set configured
        restarted = instance(open_same_store, name, configured)
        assert restarted.pipeline.anchors.version == applied.version == restarted.head().version
        assert [entry.how for entry in restarted.history().entries] == ["set", "seeded"]  # no second seed
        restarted.close()


def test_rollback_and_history_read_the_store_whichever_instance_answers(open_same_store: OpenStore) -> None:
    """A pod replaced after the swaps (its own history would be empty) rolls the fleet back through the
    store's history: the set before the active one, not a set its own past holds."""
    a = instance(open_same_store, "box-a")
    sets = [three_anchor_set(name) for name in ("one", "two", "three")]
    for anchors in sets:
        a.swap(anchors, expected=a.head().version)
    a.close()
    replacement = instance(open_same_store, "box-new")
    assert [e.version for e in replacement.history().entries] == [s.version for s in reversed(sets)] + [
        default_anchor_set().version
    ]
    target, active = replacement.rollback_target(1)
    assert (target.version, active) == (sets[1].version, sets[2].version)
    replacement.swap(target, expected=active, how="rollback")
    entries = replacement.history().entries
    assert (entries[0].version, entries[0].how, entries[0].activated_by) == (sets[1].version, "rollback", "box-new")
    replacement.close()


def test_a_forced_activation_is_marked_in_the_history(open_same_store: OpenStore) -> None:
    a = instance(open_same_store, "box-a")
    a.swap(three_anchor_set("forced"), expected=a.head().version, how="proposal", forced=True)
    a.swap(three_anchor_set("fine"), expected=a.head().version, how="proposal")
    assert [(e.how, e.forced) for e in a.history().entries] == [
        ("proposal", False),
        ("proposal", True),
        ("seeded", False),
    ]
    a.close()


def test_an_instance_state_from_before_the_store_is_imported_once(open_same_store: OpenStore, tmp_path: Path) -> None:
    state_file = tmp_path / "state" / "gcdtrav.anchors.json"
    older, newer = three_anchor_set("older"), three_anchor_set("newer")
    entries = [
        AnchorHistoryEntry(accepted_at=2000.0, version=newer.version, anchor_set=newer),
        AnchorHistoryEntry(accepted_at=1000.0, version=older.version, anchor_set=older),
    ]
    state_file.parent.mkdir()
    state_file.write_text(newer.to_json() + "\n")  # as a gcdtrav before the store left it
    history_file_of(state_file).write_text(AnchorHistoryReply(instance="old", entries=entries).model_dump_json())
    a = instance(open_same_store, "box-a", legacy=state_file)
    assert a.pipeline.anchors.version == newer.version
    recorded = [(e.version, e.accepted_at, e.how) for e in a.history().entries]
    assert recorded == [(newer.version, 2000.0, "imported"), (older.version, 1000.0, "imported")]
    assert not state_file.exists() and state_file.with_name(state_file.name + ".imported").is_file()
    a.close()
    state_file.write_text(three_anchor_set("stale").to_json())  # a state file appearing later: the store is the record
    again = instance(open_same_store, "box-a", legacy=state_file)
    assert [e.version for e in again.history().entries] == [newer.version, older.version]
    again.close()
