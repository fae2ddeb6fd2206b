"""The experience's pairs: pairing with the grid as it stood lookahead_s before, counted ignores and rejections,
concept tuples kept apart across a swap, bounds, a restart (the SQLite store; tests/service/store/ holds the
store's own suite over both backends)."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np
import pytest
from gcdtrav.schemas.anchors import Anchor, AnchorSet
from gcdtrav.schemas.experience import TraversalOutcome
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.experience.snapshots import SnapshotRing
from gcdtrav.service.experience.store import ExperienceStore, OutcomeRejected
from gcdtrav.service.grid.fusion import GridSpec, GroundGrid

from tools.loopback import sqlite_outbox

A = AnchorSet(anchors=[Anchor(concept="mud", position=0.1), Anchor(concept="grass", position=0.5)])
B = AnchorSet(anchors=[Anchor(concept="sand", position=0.2), Anchor(concept="asphalt", position=0.9)])
LOOKAHEAD = 2.0


def observe(grid: GroundGrid, x: float, y: float, weights: list[float], stamp: float, anchors: AnchorSet) -> None:
    """Fuse 50 pixels of the given weights at (x, y)."""
    points = np.tile([[x, y]], (50, 1))
    grid.add(points, np.tile(np.array(weights, np.float32)[:, None], (1, 50)), stamp, anchors)


def outcome(stamp: float, x: float = 1.05, y: float = 1.05, score: float = 0.7, **extra: object) -> TraversalOutcome:
    return TraversalOutcome(stamp=stamp, x=x, y=y, score=score, kind="velocity", **extra)  # type: ignore[arg-type]


def new_store(path: Path | None = None, max_pairs: int = 1000, max_bytes: int = 10_000_000) -> ExperienceStore:
    """Pairs of grid 'cam' in a SQLite store (a fresh one, or the file at ``path``: a restart)."""
    where = path or Path(tempfile.mkdtemp(prefix="gcdtrav-experience-")) / "store.sqlite3"
    return ExperienceStore(sqlite_outbox(where, max_pairs, max_bytes), "cam", LOOKAHEAD, "i1", clock=lambda: 99.0)


@pytest.fixture()
def world() -> tuple[GroundGrid, SnapshotRing]:
    grid = GroundGrid(GridSpec(size_m=4.0, resolution_m=0.1, half_life_s=1.0), len(A))
    return grid, SnapshotRing(every_s=0.25, budget_bytes=10_000_000, keep_s=30.0)


def test_an_outcome_pairs_with_the_cell_as_it_stood_lookahead_before(world: tuple[GroundGrid, SnapshotRing]) -> None:
    grid, ring = world
    observe(grid, 1.05, 1.05, [0.2, 0.8], 10.0, A)  # ahead of the robot: mostly grass
    ring.capture(grid)
    observe(grid, 1.05, 1.05, [0.99, 0.01], 11.9, A)  # under the robot: looks like mud now
    ring.capture(grid)
    store = new_store()
    assert store.add(outcome(12.5), ring) == 1
    pairs = store.pairs(A.concepts)
    np.testing.assert_allclose(pairs.weights_for(A)[0], [0.2, 0.8], atol=1e-3)  # the 10.0 snapshot
    assert pairs.versions == (A.version,) and pairs.outcomes[0] == 0.7 and pairs.stamps[0] == 12.5


def test_a_radius_pairs_every_known_cell_within_it(world: tuple[GroundGrid, SnapshotRing]) -> None:
    grid, ring = world
    for x in (1.05, 1.15, 1.25, 1.55):
        observe(grid, x, 1.05, [0.5, 0.5], 10.0, A)
    ring.capture(grid)
    store = new_store()
    assert store.add(outcome(12.0, x=1.15, radius_m=0.12), ring) == 3  # 1.05, 1.15, 1.25: within 0.12 m
    assert store.counts["pairs"] == 3


def test_unknown_cells_and_outcomes_before_any_prediction_are_counted_and_ignored(
    world: tuple[GroundGrid, SnapshotRing],
) -> None:
    grid, ring = world
    store = new_store()
    assert store.add(outcome(12.0), ring) == 0  # no snapshot yet
    observe(grid, 1.05, 1.05, [0.5, 0.5], 10.0, A)
    ring.capture(grid)
    assert store.add(outcome(11.0), ring) == 0  # its lookahead reaches before the first snapshot
    assert store.add(outcome(12.0, x=-1.5), ring) == 0  # a cell never observed
    assert store.add(outcome(12.0, x=50.0), ring) == 0  # outside the grid
    assert store.counts == {"outcomes": 4, "ignored_no_prediction": 2, "ignored_unknown_cell": 2}
    assert store.totals().pairs == 0


def test_a_swap_between_outcomes_keeps_the_pairs_apart(world: tuple[GroundGrid, SnapshotRing]) -> None:
    grid, ring = world
    observe(grid, 1.05, 1.05, [0.3, 0.7], 10.0, A)
    ring.capture(grid)
    store = new_store()
    store.add(outcome(12.0, score=0.6), ring)
    observe(grid, 1.05, 1.05, [0.9, 0.1], 13.0, B)  # the swap resets the grid
    ring.capture(grid)
    store.add(outcome(15.0, score=0.2), ring)
    reordered = AnchorSet(anchors=[Anchor(concept="grass", position=0.5), Anchor(concept="mud", position=0.6)])
    assert store.tuples() == [("asphalt", "sand"), ("grass", "mud")]
    assert store.pairs(A.concepts).outcomes.tolist() == [0.6]
    assert store.pairs(B.concepts).outcomes.tolist() == [0.2]
    np.testing.assert_allclose(store.pairs(reordered.concepts).weights_for(reordered)[0], [0.7, 0.3], atol=1e-3)
    report = store.report(A, tau=0.3)
    assert report.figures.pairs == 1 and report.pairs_by_version == {A.version: 1}
    assert report.figures.mae == pytest.approx(abs(0.3 * 0.1 + 0.7 * 0.5 - 0.6), abs=1e-3)


def test_bad_outcome_messages_are_rejected_with_a_reason_and_counted(world: tuple[GroundGrid, SnapshotRing]) -> None:
    _, ring = world
    store = new_store()
    bad = {
        b"\xc1garbage": "bad_outcome",
        json.dumps({"stamp": 1, "x": 0, "y": 0, "score": 1.5, "kind": "velocity"}).encode(): "bad_outcome",
        json.dumps({"stamp": 1, "x": 0, "y": 0, "score": 0, "kind": "teleport"}).encode(): "bad_outcome",
        b'{"stamp": NaN, "x": 0, "y": 0, "score": 0.5, "kind": "contact"}': "bad_outcome",
        json.dumps({"stamp": 1, "x": 0, "y": 0, "score": 0, "kind": "contact", "radius_m": 99}).encode(): "bad_outcome",
        b"[1, 2]": "bad_outcome",
        b"{" + b" " * 5000 + b"}": "oversized",
    }  # fmt: skip
    for payload, reason in bad.items():
        with pytest.raises(OutcomeRejected) as caught:
            store.ingest(payload, ring)
        assert caught.value.reason == reason
    assert store.counts == {"rejected_bad_outcome": 6, "rejected_oversized": 1}
    good = json.dumps({"stamp": 12, "x": 1.05, "y": 1.05, "score": 0.5, "kind": "operator", "new": 1}).encode()
    assert store.ingest(good, ring) == 0  # decodes (unknown field ignored); no snapshot: ignored, not rejected
    assert store.counts["ignored_no_prediction"] == 1


def test_the_store_is_bounded_by_count_and_bytes_oldest_first(world: tuple[GroundGrid, SnapshotRing]) -> None:
    grid, ring = world
    observe(grid, 1.05, 1.05, [0.5, 0.5], 10.0, A)
    ring.capture(grid)
    store = new_store(max_pairs=3)
    for k in range(5):
        store.add(outcome(12.0 + k, score=k / 10), ring)
        store.outbox.flush(5.0)  # one append each: the bound applies at every append
    assert store.pairs(A.concepts).outcomes.tolist() == [0.2, 0.3, 0.4] and store.outbox.state().evicted == 2
    per_pair = store.totals().bytes // store.totals().pairs
    by_bytes = new_store(max_bytes=2 * per_pair)
    for k in range(5):
        by_bytes.add(outcome(12.0 + k, score=k / 10), ring)
    by_bytes.outbox.flush(5.0)
    assert by_bytes.totals().pairs == 2 and by_bytes.totals().bytes <= 2 * per_pair


def test_pairs_survive_a_restart(tmp_path: Path, world: tuple[GroundGrid, SnapshotRing]) -> None:
    grid, ring = world
    observe(grid, 1.05, 1.05, [0.25, 0.75], 10.0, A)
    ring.capture(grid)
    path = tmp_path / "state" / "gcdtrav.store.sqlite3"
    store = new_store(path)
    store.add(outcome(12.0, score=0.4), ring)
    store.add(outcome(13.0, score=0.9), ring)
    before = store.pairs(A.concepts)
    store.outbox.close()
    again = new_store(path)
    after = again.pairs(A.concepts)
    np.testing.assert_array_equal(before.weights, after.weights)
    assert after.outcomes.tolist() == [0.4, 0.9] and after.versions == before.versions
    again.add(outcome(14.0, score=0.1), ring)  # appended after the restart's
    assert again.pairs(A.concepts).outcomes.tolist() == [0.4, 0.9, 0.1]
    assert again.columns(A.concepts).sources == ("cam",) * 3


def test_experience_is_off_by_default() -> None:
    settings = ServiceSettings()
    assert not settings.experience.enabled and not settings.ask.enabled
    with pytest.raises(ValueError, match="give both cmd_vel and odometry"):
        ServiceSettings.model_validate({"experience": {"enabled": True, "cmd_vel": "/cmd_vel"}})
    with pytest.raises(ValueError, match="Extra inputs"):
        ServiceSettings.model_validate({"experience": {"lookahed_s": 2}})


def test_the_settings_in_docs_calibration_md_are_valid() -> None:
    import yaml

    text = (Path(__file__).resolve().parents[3] / "docs" / "calibration.md").read_text("utf-8")
    block = text.split("## Settings", 1)[1].split("```yaml", 1)[1].split("```", 1)[0]
    settings = ServiceSettings.model_validate(yaml.safe_load(block))
    defaults = ServiceSettings()
    assert settings.ask == defaults.ask  # the page shows the defaults
    shown = settings.experience.model_copy(update={"cmd_vel": None, "odometry": None})
    assert shown == defaults.experience and settings.experience.cmd_vel == "/cmd_vel"
