"""No single robot steers the fleet's experience (issue 58): each robot's share of the graded and fitted pairs
capped, an operator's exclusion honoured, a flood of invented outcomes bounded by the cap."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest
from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.service.experience.fitter import FitOptions
from gcdtrav.service.experience.sharing import fleet_mask, kept_counts, robot_of
from gcdtrav.service.experience.store import ExperienceStore
from gcdtrav.service.store import PairRecord, concept_key

from tools.loopback import sqlite_outbox

ANCHORS = default_anchor_set()


@pytest.mark.parametrize(
    ("counts", "share", "kept"),
    [
        ({"a": 1000, "b": 100, "c": 100, "d": 100, "e": 100}, 1.0, {"a": 1000, "b": 100, "c": 100, "d": 100, "e": 100}),
        ({"a": 5}, 0.25, {"a": 5}),  # one robot: all of its pairs
        ({"a": 1000, "b": 100}, 0.25, {"a": 100, "b": 100}),  # two robots cannot both hold <= 25 %: equal shares
        ({"a": 100, "b": 100, "c": 100, "d": 100}, 0.25, {"a": 100, "b": 100, "c": 100, "d": 100}),  # exactly 1/4
        ({"a": 1000, "b": 1000, "c": 10, "d": 10, "e": 10}, 0.25, {"a": 15, "b": 15, "c": 10, "d": 10, "e": 10}),
        ({}, 0.25, {}),
    ],
)
def test_kept_counts_at_the_edges(counts: dict[str, int], share: float, kept: dict[str, int]) -> None:
    assert kept_counts(counts, share) == kept


def test_no_robot_holds_more_than_the_cap_and_robots_under_it_keep_everything() -> None:
    rng = np.random.default_rng(3)
    for _ in range(200):
        counts = {f"r{i}": int(n) for i, n in enumerate(rng.integers(1, 5000, rng.integers(5, 12)))}
        share = float(rng.uniform(0.15, 0.6))
        kept = kept_counts(counts, share)
        total = sum(kept.values())
        cap = max(share, 1 / len(counts))  # fewer robots than 1 / share: equal shares
        assert max(kept.values()) <= cap * total + 1  # + 1: whole pairs
        if share > 1 / len(counts):
            assert all(kept[r] == n for r, n in counts.items() if n <= share * total)


def test_a_robots_cameras_count_as_one_robot_and_excluded_robots_not_at_all() -> None:
    assert robot_of("r7/front") == robot_of("r7") == "r7"
    sources = ["r7/front"] * 300 + ["r7/rear"] * 300 + [f"r{i}" for i in range(1, 5) for _ in range(100)] + ["x"] * 50
    mask, shares = fleet_mask(sources, 0.25, excluded={"x"})
    assert set(shares) == {"r1", "r2", "r3", "r4", "r7"} and shares["r7"] <= 0.25
    assert not mask[-50:].any() and abs(sum(shares.values()) - 1.0) < 1e-3
    again, _ = fleet_mask(sources, 0.25, excluded={"x"})
    np.testing.assert_array_equal(mask, again)  # a report repeats itself


def drive(store: ExperienceStore, robot: str, n: int, seed: int, invented: bool = False) -> None:
    """``n`` pairs of ``robot``: honest outcomes follow the prediction's T (mean of the anchors by weight);
    invented ones say every place was impassable (0), to make the fleet distrust all of it."""
    rng = np.random.default_rng(seed)
    positions = np.array([a.position for a in ANCHORS.anchors])
    weights = rng.dirichlet(np.full(len(ANCHORS), 0.3), n).astype(np.float32)
    truth = weights @ positions
    outcomes = np.zeros(n) if invented else np.clip(truth + rng.normal(0, 0.05, n), 0, 1)
    key = concept_key(ANCHORS.concepts)  # the store's order of the concepts
    stored = weights[:, [ANCHORS.concepts.index(c) for c in key]]
    records = [PairRecord(key, w, float(o), 100.0 + i, 0, ANCHORS.version, robot, "i1")
               for i, (w, o) in enumerate(zip(stored, outcomes, strict=True))]  # fmt: skip
    assert store.outbox.put(records) == n


def fleet(share: float) -> ExperienceStore:
    where = Path(tempfile.mkdtemp(prefix="gcdtrav-sharing-")) / "store.sqlite3"
    outbox = sqlite_outbox(where, 100_000, 10**9)
    return ExperienceStore(outbox, "r1", 2.0, "i1", clock=lambda: 500.0, max_robot_share=share)


def test_a_flood_of_invented_outcomes_moves_calibration_by_no_more_than_the_cap() -> None:
    """Four honest robots, 400 pairs each; r7 invents 8,000 outcomes (20 x any other), all impassable.
    Bias and MAE are means over pairs in [0, 1]: a robot holding at most 25 % moves each by at most 0.25.
    Without the cap r7 holds 83 % and drags both far past that."""
    honest = fleet(0.25)
    for i in range(1, 5):
        drive(honest, f"r{i}", 400, seed=i)
    before = honest.report(ANCHORS, 0.3).figures
    moved = {}
    for share in (0.25, 1.0):
        flooded = fleet(share)
        for i in range(1, 5):
            drive(flooded, f"r{i}", 400, seed=i)
        drive(flooded, "r7/front", 8000, seed=7, invented=True)
        report = flooded.report(ANCHORS, 0.3)
        assert report.share_by_robot["r7"] <= share + 1e-3
        moved[share] = max(abs(report.figures.bias - before.bias), abs(report.figures.mae - before.mae))  # type: ignore[operator]
    assert moved[0.25] <= 0.25, moved
    assert moved[1.0] > 0.25, moved  # the check can tell


def test_an_excluded_robot_counts_nowhere_until_included_again_and_proposals_show_the_shares() -> None:
    store = fleet(0.25)
    for i in range(1, 5):
        drive(store, f"r{i}", 300, seed=i)
    drive(store, "r7", 3000, seed=7, invented=True)
    words = store.exclude("r7", True, actor="alice", reason="invented outcomes")
    assert [(w.robot, w.excluded, w.actor) for w in words] == [("r7", True, "alice")]
    report = store.report(ANCHORS, 0.3)
    assert report.excluded_robots == ["r7"] and "r7" not in report.pairs_by_source and report.figures.pairs == 1200
    options = FitOptions(tau=0.3, held_out_fraction=0.3, min_pairs_per_anchor=5)
    proposal = store.propose("r1", ANCHORS, options)
    assert proposal.excluded_robots == ["r7"] and set(proposal.share_by_robot) == {"r1", "r2", "r3", "r4"}
    assert proposal.train_pairs + proposal.held_out_pairs == 1200
    store.exclude("r7", False, actor="bob", reason="checked")
    again = store.report(ANCHORS, 0.3)
    assert again.excluded_robots == [] and 0.24 <= again.share_by_robot["r7"] <= 0.25
