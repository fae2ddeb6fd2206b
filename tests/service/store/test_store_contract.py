"""The Store contract, on SQLite and PostgreSQL alike: pairs kept apart by tuple and source, fleet-wide bounds
oldest first, the anchor history and its compare-and-swap, kept proposals, the schema version."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from gcdtrav.schemas.anchors import Anchor, AnchorSet, default_anchor_set
from gcdtrav.service.store import PairRecord, SchemaTooNew, Store, pair_bytes
from gcdtrav.service.store.records import AppendResult
from gcdtrav.service.store.schema import SCHEMA_VERSION
from store_test_helpers import pair, proposal_of

GRASS = ("grass", "gravel", "rock")


def test_pairs_come_back_as_appended_oldest_first(store: Store) -> None:
    records = [pair(GRASS, k, outcome=k / 10) for k in range(10)]
    result = store.append_pairs(records, max_pairs=100, max_bytes=10**6)
    assert (result.stored, result.evicted) == (10, 0)
    got = store.pairs(["rock", "grass", "gravel"])  # any order of the same concepts
    assert got.concepts == GRASS
    np.testing.assert_allclose(got.outcomes, [k / 10 for k in range(10)])
    np.testing.assert_array_equal(got.weights, np.stack([r.weights for r in records]))
    assert list(got.ids) == sorted(got.ids)
    assert got.versions == tuple(r.anchor_version for r in records)
    assert got.sources == tuple(r.source for r in records)
    assert set(got.kinds) == {0, 1}
    assert store.totals().pairs == 10 and store.totals().bytes == 10 * pair_bytes(3)


def test_tuples_and_sources_stay_apart(store: Store) -> None:
    other = ("mud", "sand")
    store.append_pairs([pair(GRASS, 0, source="a"), pair(other, 1, source="a"), pair(GRASS, 2, source="b")], 100, 10**6)
    assert store.tuples() == [GRASS, other]
    assert len(store.pairs(GRASS)) == 2 and len(store.pairs(other)) == 1
    assert store.pairs(GRASS, source="b").sources == ("b",)
    assert len(store.pairs(GRASS, source="nobody")) == 0
    assert len(store.pairs(("never", "seen"))) == 0


def test_bounds_hold_fleet_wide_oldest_first(open_same_store) -> None:  # type: ignore[no-untyped-def]
    one, two = open_same_store(), open_same_store()  # two instances on one store
    one.append_pairs([pair(GRASS, k, outcome=0.0) for k in range(6)], max_pairs=8, max_bytes=10**6)
    result = two.append_pairs([pair(("mud", "sand"), k, outcome=1.0) for k in range(4)], max_pairs=8, max_bytes=10**6)
    assert result.evicted == 2
    assert one.totals().pairs == 8
    assert len(one.pairs(GRASS)) == 4  # the two oldest, of another tuple, went first
    # Bytes bound: a 3-concept pair costs more than a 2-concept one; keep at most 3 of them.
    result = one.append_pairs([pair(GRASS, 9)], max_pairs=100, max_bytes=3 * pair_bytes(3))
    assert one.totals().bytes <= 3 * pair_bytes(3)
    assert one.totals().pairs == 3 and result.evicted == 6


def test_bound_of_one_pair(store: Store) -> None:
    for k in range(3):
        store.append_pairs([pair(GRASS, k, outcome=k / 4)], max_pairs=1, max_bytes=10**6)
    assert store.totals().pairs == 1
    assert list(store.pairs(GRASS).outcomes) == [0.5]


def test_nothing_to_append(store: Store) -> None:
    assert store.append_pairs([], 10, 10**6).stored == 0
    assert store.totals().pairs == 0 and store.tuples() == []


def test_appends_from_many_threads_lose_nothing(open_same_store) -> None:  # type: ignore[no-untyped-def]
    stores = [open_same_store() for _ in range(3)]

    def append(store: Store, start: int) -> None:
        for k in range(start, start + 20):
            store.append_pairs([pair(GRASS, k)], 10**6, 10**9)

    threads = [threading.Thread(target=append, args=(s, 100 * i)) for i, s in enumerate(stores)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert stores[0].totals().pairs == 60 == len(stores[0].pairs(GRASS))


def test_pairs_survive_reopening(open_same_store) -> None:  # type: ignore[no-untyped-def]
    first = open_same_store()
    first.append_pairs([pair(GRASS, k) for k in range(5)], 100, 10**6)
    first.close()
    again = open_same_store()
    assert len(again.pairs(GRASS)) == 5


# ---- anchor sets ----------------------------------------------------------------------------------------------


def _set(position: float) -> AnchorSet:
    return AnchorSet(
        name=f"at {position}",
        default_width=0.1,
        anchors=[Anchor(concept="rock", position=0.0), Anchor(concept="grass", position=position)],
    )


def test_seed_only_fills_an_empty_store(store: Store) -> None:
    assert store.active() is None and store.history() == []
    seeded = store.seed(default_anchor_set(), "i1")
    assert seeded.how == "seeded" and seeded.accepted_at == 0.0
    again = store.seed(_set(0.9), "i2")  # a second instance with another configured set
    assert again.version == default_anchor_set().version
    assert store.active() == seeded and len(store.history()) == 1


def test_activation_is_compare_and_swap(open_same_store) -> None:  # type: ignore[no-untyped-def]
    one, two = open_same_store(), open_same_store()
    start = one.seed(_set(0.5), "i1")
    won = one.activate(_set(0.8), start.version, "set", "i1", actor="ana")
    lost = two.activate(_set(0.7), start.version, "set", "i2", actor="bo")
    assert won.applied and not lost.applied
    assert lost.active.version == _set(0.8).version and lost.active.actor == "ana"
    assert two.active() == won.active
    forced = two.activate(_set(0.7), None, "proposal", "i2", forced=True)  # unconditional
    assert forced.applied and forced.active.forced and forced.active.how == "proposal"
    history = one.history()
    assert [h.version for h in history] == [_set(0.7).version, _set(0.8).version, start.version]
    assert [h.entry for h in history] == sorted((h.entry for h in history), reverse=True)
    assert history[0].anchor_set == _set(0.7)
    assert len(one.history(limit=1)) == 1


def test_of_concurrent_activations_exactly_one_wins(open_same_store) -> None:  # type: ignore[no-untyped-def]
    stores = [open_same_store() for _ in range(4)]
    start = stores[0].seed(_set(0.5), "i0")
    results: list[object] = [None] * len(stores)
    barrier = threading.Barrier(len(stores))

    def activate(k: int) -> None:
        barrier.wait()
        results[k] = stores[k].activate(_set(0.6 + k / 20), start.version, "set", f"i{k}")

    threads = [threading.Thread(target=activate, args=(k,)) for k in range(len(stores))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    winners = [r for r in results if r.applied]  # type: ignore[attr-defined]
    assert len(winners) == 1
    assert all(r.active.version == winners[0].active.version for r in results)  # type: ignore[attr-defined]
    assert len(stores[0].history()) == 2


def test_proposals_are_kept_by_version(store: Store) -> None:
    first, second = proposal_of(_set(0.5), _set(0.6)), proposal_of(_set(0.5), _set(0.7))
    store.put_proposal(first, "i1")
    stored = store.put_proposal(second, "i2")
    assert stored.version == _set(0.7).version
    assert store.proposal(_set(0.6).version).proposal == first  # type: ignore[union-attr]
    assert store.proposal("nope") is None
    store.put_proposal(first, "i3")  # the same version again replaces it
    assert store.proposal(_set(0.6).version).instance == "i3"  # type: ignore[union-attr]
    assert store.proposal(_set(0.7).version).instance == "i2"  # type: ignore[union-attr]


# ---- the schema ---------------------------------------------------------------------------------------------


def test_a_newer_schema_is_refused_untouched(open_same_store) -> None:  # type: ignore[no-untyped-def]
    store = open_same_store()
    store.append_pairs([pair(GRASS, 0)], 10, 10**6)
    with store._transaction("schema") as cursor:  # type: ignore[attr-defined]
        cursor.execute("UPDATE schema_version SET version = 99")
    with pytest.raises(SchemaTooNew) as refused:
        open_same_store()
    message = str(refused.value)
    assert "schema version 99" in message and f"up to {SCHEMA_VERSION}" in message and "\n" not in message
    with store._transaction(None) as cursor:  # type: ignore[attr-defined]
        cursor.execute("SELECT version FROM schema_version")
        assert cursor.fetchone()[0] == 99


def test_pair_record_weights_keep_float32(store: Store) -> None:
    record = PairRecord(GRASS, np.array([0.1, 0.2, 0.7], np.float32), 0.5, 1.0, 0, "v", "cam")
    store.append_pairs([record], 10, 10**6)
    assert store.pairs(GRASS).weights.dtype == np.float32


def test_a_batch_appended_again_under_its_id_stores_nothing(store: Store) -> None:
    """The outbox's replay of a batch whose commit's answer was lost (tests/service/store/test_replayed_batch.py
    cuts it for real): the second append under the same id stores nothing, another id stores again."""
    batch = [pair(GRASS, k) for k in range(5)]
    assert store.append_pairs(batch, 100, 10**6, batch_id="b1") == AppendResult(5, 0)
    assert store.append_pairs(batch, 100, 10**6, batch_id="b1") == AppendResult(0, 0, replayed=True)
    assert store.append_pairs(batch, 100, 10**6, batch_id="b2").stored == 5
    assert store.append_pairs(batch, 100, 10**6).stored == 5  # no id: no check (the legacy import)
    assert len(store.pairs(GRASS)) == 15 and store.totals().pairs == 15


def test_exclusions_are_recorded_and_the_newest_word_per_robot_is_in_force(open_same_store) -> None:  # type: ignore[no-untyped-def]
    from gcdtrav.service.store import Exclusion

    one, two = open_same_store(), open_same_store()  # another instance sees the same words
    assert one.exclusions() == []
    one.exclude(Exclusion("r7", True, 10.0, "alice", "invented outcomes", "i1"))
    one.exclude(Exclusion("r8", True, 11.0, "alice", "", "i1"))
    two.exclude(Exclusion("r8", False, 12.0, "bob", "fixed", "i2"))
    assert [(e.robot, e.excluded, e.actor, e.reason, e.instance) for e in one.exclusions()] == [
        ("r7", True, "alice", "invented outcomes", "i1"),
        ("r8", False, "bob", "fixed", "i2"),
    ]


def test_calibration_sums_add_up_per_hour_and_for_all_hours_behind_a_watermark(open_same_store) -> None:  # type: ignore[no-untyped-def]
    from gcdtrav.service.store import SumsRow
    from gcdtrav.service.store.records import ALL_HOURS, HOURS_KEPT

    one, two = open_same_store(), open_same_store()
    hour = int(one.clock() // 3600)
    rows = [SumsRow("v1", "r1", 0, hour, np.array([1.0, 2.0])), SumsRow("v1", "r1", 0, hour - 1, np.array([3.0, 4.0]))]
    assert one.graded_upto("v2@0.3") == 0
    assert one.add_sums("v2@0.3", rows, from_id=0, upto_id=7)
    assert not two.add_sums("v2@0.3", rows, from_id=0, upto_id=7)  # the other instance came first: nothing added
    assert two.graded_upto("v2@0.3") == 7
    everything = two.sums("v2@0.3")
    assert [(r.hour, list(r.sums)) for r in everything] == [(ALL_HOURS, [4.0, 6.0])]
    assert sorted((r.hour, list(r.sums)) for r in two.sums("v2@0.3", since_hour=hour)) == [(hour, [1.0, 2.0])]
    assert two.add_sums("v2@0.3", [SumsRow("v1", "r1", 0, -2, np.array([1.0, 1.0]))], from_id=7, upto_id=9)  # all only
    old = SumsRow("v1", "r2", 1, hour - HOURS_KEPT - 5, np.array([1.0, 1.0]))
    assert two.add_sums("v2@0.3", [old], from_id=9, upto_id=10)
    assert {(r.source, r.hour) for r in two.sums("v2@0.3", since_hour=0)} == {("r1", hour), ("r1", hour - 1)}
    assert sorted(list(r.sums) for r in two.sums("v2@0.3")) == [[1.0, 1.0], [5.0, 7.0]]
    assert two.sums("other@0.3") == []


def test_pairs_older_than_the_age_bound_go_and_contents_say_what_is_kept(store: Store) -> None:
    now = store.clock()
    store.clock = lambda: now - 10 * 86_400.0  # type: ignore[method-assign]
    store.append_pairs([pair(GRASS, k, source="r1") for k in range(4)], 100, 10**6)
    store.clock = lambda: now  # type: ignore[method-assign]
    result = store.append_pairs([pair(GRASS, 10 + k, source="r2") for k in range(3)], 100, 10**6, max_age_s=86_400.0)
    assert result.evicted == 4 and store.totals().pairs == 3 and store.totals().bytes == 3 * pair_bytes(3)
    [kept] = store.contents()
    assert (kept.source, kept.pairs, kept.bytes) == ("r2", 3, 3 * pair_bytes(3))
    assert abs(kept.oldest - now) < 1 and abs(kept.newest - now) < 1
    assert store.append_pairs([pair(GRASS, 20)], 100, 10**6, max_age_s=86_400.0).evicted == 0
    assert store.graded_keys() == {}
