"""Calibration from sums kept as pairs arrive (issue 57): the report equals the direct computation over the
raw pairs, whichever way the pairs came (graded as they were paired, or caught up after a swap), outlives
the pairs the bounds evict, counts each pair once with two instances catching up, and has windows."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from gcdtrav.schemas.anchors import Anchor, AnchorSet
from gcdtrav.schemas.experience import TraversalOutcome
from gcdtrav.service.experience.calibration import calibration_figures
from gcdtrav.service.experience.store import ExperienceStore, as_pairs

from tools.loopback import sqlite_outbox

TAU = 0.3
A = AnchorSet(anchors=[Anchor(concept="mud", position=0.1), Anchor(concept="grass", position=0.6),
                       Anchor(concept="asphalt", position=0.95, width=0.05)])  # fmt: skip
SWAPPED = AnchorSet(anchors=[Anchor(concept="mud", position=0.2), Anchor(concept="grass", position=0.5, width=0.1),
                             Anchor(concept="asphalt", position=0.9)])  # fmt: skip


def store_at(path: Path, max_pairs: int = 100_000, tau: float | None = TAU, source: str = "r1") -> ExperienceStore:
    return ExperienceStore(sqlite_outbox(path, max_pairs, 10**9), source, 2.0, "i1", clock=lambda: 9.0, tau=tau)


def drive(store: ExperienceStore, anchors: AnchorSet, n: int, seed: int, kind: str = "velocity") -> None:
    rng = np.random.default_rng(seed)
    for k in range(n):
        weights = rng.dirichlet(np.full(len(anchors), 0.5), 3)
        score = float(rng.uniform())
        outcome = TraversalOutcome(stamp=100.0 + k, x=0.0, y=0.0, score=score, kind=kind)  # type: ignore[arg-type]
        assert store.add_predicted(weights, anchors, outcome) == 3


def direct(store: ExperienceStore, anchors: AnchorSet) -> dict[str, object]:
    pairs = as_pairs(store.columns(anchors.concepts))
    return calibration_figures(pairs.weights_for(anchors), pairs.outcomes, anchors, TAU).model_dump()


def _close(got: object, want: object) -> bool:
    if isinstance(want, dict):
        assert isinstance(got, dict) and got.keys() == want.keys(), (got, want)
        return all(_close(got[k], want[k]) for k in want)
    if isinstance(want, list):
        assert isinstance(got, list) and len(got) == len(want)
        return all(_close(g, w) for g, w in zip(got, want, strict=True))
    if isinstance(want, float):
        assert got == pytest.approx(want, rel=1e-9, abs=1e-12), (got, want)
        return True
    assert got == want, (got, want)
    return True


def test_the_report_equals_the_direct_computation_before_and_after_a_swap(tmp_path: Path) -> None:
    store = store_at(tmp_path / "s.sqlite3")
    drive(store, A, 40, seed=1)
    legacy = store_at(tmp_path / "s.sqlite3", tau=None)  # another instance that grades nothing at append
    drive(legacy, A, 15, seed=2, kind="contact")
    assert legacy.outbox.flush(5.0)
    report = store.report(A, TAU)
    _close(report.figures.model_dump(), direct(store, A))
    assert report.figures.pairs == 165 and report.pairs_by_kind == {"contact": 45, "velocity": 120}
    drive(store, SWAPPED, 20, seed=3)  # after a swap: the new set grades the older pairs by the catch-up
    swapped = store.report(SWAPPED, TAU)
    _close(swapped.figures.model_dump(), direct(store, SWAPPED))
    assert swapped.figures.pairs == 225 and swapped.pairs_by_version == {A.version: 165, SWAPPED.version: 60}
    again = store.report(A, TAU)  # the old set's sums caught up with the new pairs too
    _close(again.figures.model_dump(), direct(store, A))


def test_the_sums_outlive_the_pairs_the_bounds_evict(tmp_path: Path) -> None:
    store = store_at(tmp_path / "s.sqlite3", max_pairs=30)
    drive(store, A, 50, seed=4)
    report = store.report(A, TAU)
    assert len(store.columns(A.concepts)) == 30 and report.figures.pairs == 150  # the whole history graded


def test_two_instances_catching_up_at_once_count_each_pair_once(tmp_path: Path) -> None:
    first, second = store_at(tmp_path / "s.sqlite3"), store_at(tmp_path / "s.sqlite3")
    drive(first, A, 30, seed=5)
    reports = [first.report(SWAPPED, TAU), second.report(SWAPPED, TAU), first.report(SWAPPED, TAU)]
    assert [r.figures.pairs for r in reports] == [90, 90, 90]
    _close(reports[1].figures.model_dump(), direct(first, SWAPPED))


def test_windows_count_the_pairs_appended_within_them(tmp_path: Path) -> None:
    store = store_at(tmp_path / "s.sqlite3")
    db = store.outbox.store
    assert db is not None
    now = db.clock()
    db.clock = lambda: now - 3 * 86_400.0  # three days ago: kept in all hours only
    drive(store, A, 5, seed=6)
    store.outbox.flush(5.0)
    db.clock = lambda: now - 5 * 3600.0  # five hours ago: within the day
    drive(store, A, 7, seed=7)
    store.outbox.flush(5.0)
    db.clock = lambda: now
    drive(store, A, 11, seed=8)
    counts = {window: store.report(A, TAU, window=window).figures.pairs for window in ("all", "day", "hour")}
    assert counts == {"all": 69, "day": 54, "hour": 33}


def test_a_proposal_is_fitted_on_the_sample_of_the_whole_history(tmp_path: Path) -> None:
    """The raw pairs keep the last 90; the fit and its judgement use the 600-pair sample of all 900."""
    from gcdtrav.service.experience.fitter import FitOptions
    from gcdtrav.service.store.outbox import PairOutbox
    from gcdtrav.service.store.sqlite import SqliteStore

    path = tmp_path / "s.sqlite3"
    outbox = PairOutbox(lambda: SqliteStore(path), "sqlite", str(path), 100_000, 90, 10**9, sample_size=600)
    outbox.open_now()
    outbox.start()
    store = ExperienceStore(outbox, "r1", 2.0, "i1", clock=lambda: 9.0, tau=TAU)
    drive(store, A, 300, seed=9)  # 900 pairs, stamps 100..399
    proposal = store.propose("r1", A, FitOptions(tau=TAU, held_out_fraction=0.3, min_pairs_per_anchor=5))
    assert len(store.columns(A.concepts)) == 90
    assert proposal.train_pairs + proposal.held_out_pairs == 600
    assert proposal.pairs_from is not None and proposal.pairs_from < 200  # reaches back before the kept 30 s


def test_after_an_upgrade_a_source_is_fitted_on_its_retained_pairs_until_its_sample_holds_as_many() -> None:
    from gcdtrav.service.experience.store import sampled_history
    from gcdtrav.service.store import PairColumns

    def columns(sources: list[str]) -> PairColumns:
        n = len(sources)
        weights = np.full((n, 2), 0.5, np.float32)
        stamps = np.arange(n, dtype=float)
        return PairColumns(("a", "b"), np.arange(n), weights, np.zeros(n), stamps, np.zeros(n, np.uint8), ("v",) * n,
                           tuple(sources))  # fmt: skip

    retained = columns(["r1"] * 100 + ["r2"] * 300 + ["r3"] * 10)
    sample = columns(["r1"] * 5 + ["r2"] * 50 + ["r3"] * 10 + ["r4"] * 7)  # r1 sampled only since the upgrade
    chosen = sampled_history(retained, sample, size=50)
    assert Counter(chosen.sources) == {"r1": 100, "r2": 50, "r3": 10, "r4": 7}
    assert len(sampled_history(retained, columns([]), size=0)) == len(retained)  # no sample: the retained pairs
