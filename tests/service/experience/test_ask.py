"""Asking an operator: cells ahead that stay ambiguous or novel make one question, rate-limited; an answer
becomes operator outcomes paired with what the question showed, and closes it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from gcdtrav.schemas.anchors import Anchor, AnchorSet
from gcdtrav.schemas.experience import OperatorAnswer
from gcdtrav.schemas.experience import answer_score as parse_answer
from gcdtrav.schemas.messages import Pose2D
from gcdtrav.schemas.settings import AskSettings
from gcdtrav.service.experience.ask import OperatorAsker, corridor
from gcdtrav.service.experience.store import ExperienceStore
from gcdtrav.service.grid.fusion import GridSpec, GroundGrid

from tools.loopback import sqlite_outbox

ANCHORS = AnchorSet(anchors=[Anchor(concept="mud", position=0.1), Anchor(concept="grass", position=0.8)])
SETTINGS = AskSettings(enabled=True, range_m=3.0, width_m=1.0, persist_s=1.0, min_cells=3, min_interval_s=10.0)
POSE = Pose2D(stamp=0.0, x=0.0, y=0.0, yaw=0.0)  # facing +x


def observe(grid: GroundGrid, xs: list[float], weights: list[float], stamp: float, match: float = 0.9) -> None:
    points = np.array([[x, 0.05] for x in xs for _ in range(10)])
    w = np.tile(np.array(weights, np.float32)[:, None], (1, len(points)))
    grid.add(points, w, stamp, ANCHORS, np.full(len(points), match))


def new_grid() -> GroundGrid:
    return GroundGrid(GridSpec(size_m=10.0, resolution_m=0.1, half_life_s=5.0), 2)


AHEAD = [1.05, 1.15, 1.25, 1.35]


def test_persistent_ambiguity_ahead_asks_once_with_the_two_competing_concepts() -> None:
    grid, asker = new_grid(), OperatorAsker("cam", SETTINGS, tau=0.3)
    observe(grid, AHEAD, [0.5, 0.5], 0.0)  # U 0.35, P(T < 0.3) 0.5: ambiguous
    observe(grid, [-1.05, -1.15, -1.25], [0.5, 0.5], 0.0)  # behind the robot: never asked about
    assert asker.update(grid, POSE) is None  # not for persist_s yet
    observe(grid, AHEAD, [0.5, 0.5], 0.5)
    assert asker.update(grid, POSE) is None
    observe(grid, AHEAD, [0.5, 0.5], 1.2)
    crops: list[tuple[float, float, float, float]] = []
    question = asker.update(grid, POSE, crop=lambda region: crops.append(region) or b"jpeg")
    assert question is not None and question.reason == "ambiguous" and question.crop_jpeg == b"jpeg"
    assert sorted(c.concept for c in question.concepts) == ["grass", "mud"]
    assert [c.weight for c in question.concepts] == pytest.approx([0.5, 0.5], abs=1e-3)
    assert len(question.cells) == 4 and all(x > 0 for x, _ in question.cells)
    assert question.region == pytest.approx((1.0, 0.0, 1.4, 0.1), abs=1e-6) and crops == [question.region]
    assert question.p_below == pytest.approx(0.5, abs=1e-3)
    observe(grid, AHEAD, [0.5, 0.5], 1.5)
    assert asker.update(grid, POSE) is None  # one question open at a time
    assert asker.open_question == question and asker.counts == {"asked": 1}


def test_clear_ground_never_asks_and_a_flicker_starts_over() -> None:
    grid, asker = new_grid(), OperatorAsker("cam", SETTINGS, tau=0.3)
    for k in range(5):
        observe(grid, AHEAD, [0.02, 0.98], k * 0.5)  # grass: U 0.1, P(T < 0.3) 0.02
        assert asker.update(grid, POSE) is None
    flicker = OperatorAsker("cam", SETTINGS, tau=0.3)
    for k in range(6):
        weights = [0.5, 0.5] if k % 2 == 0 else [0.02, 0.98]
        fresh = new_grid()
        observe(fresh, AHEAD, weights, k * 0.5)
        assert flicker.update(fresh, POSE) is None  # never ambiguous for persist_s on end


def test_novel_ground_asks_too() -> None:
    grid, asker = new_grid(), OperatorAsker("cam", SETTINGS, tau=0.3)
    for stamp in (0.0, 1.1):
        observe(grid, AHEAD, [0.02, 0.98], stamp, match=0.05)  # confident weights, but nothing matches
        question = asker.update(grid, POSE)
    assert question is not None and question.reason == "novel"
    assert question.match == pytest.approx(0.05, abs=1e-3)


def test_an_answer_becomes_operator_outcomes_and_closes_the_question(tmp_path: Path) -> None:
    grid, asker = new_grid(), OperatorAsker("cam", SETTINGS, tau=0.3)
    for stamp in (0.0, 1.1):
        observe(grid, AHEAD, [0.5, 0.5], stamp)
        question = asker.update(grid, POSE)
    assert question is not None
    with pytest.raises(ValueError, match="no open question 'cam-9'"):
        asker.answer(OperatorAnswer(id="cam-9", source="cam", score=1.0), 5.0)
    answered = asker.answer(OperatorAnswer(id=question.id, source="cam", score=parse_answer("blocked")), 5.0)
    assert [o.kind for o in answered.outcomes] == ["operator"] * 4 and {o.score for o in answered.outcomes} == {0.0}
    assert [(o.x, o.y) for o in answered.outcomes] == question.cells and answered.outcomes[0].stamp == 5.0
    store = ExperienceStore(sqlite_outbox(tmp_path / "store.sqlite3", 100, 10**6), "cam", 2.0)
    assert store.add_predicted(answered.weights, answered.anchors, answered.outcomes[0]) == 4
    assert store.pairs(ANCHORS.concepts).weights_for(ANCHORS)[0] == pytest.approx([0.5, 0.5], abs=1e-3)
    assert asker.open_question is None
    assert asker.counts == {"asked": 1, "unknown_answer": 1, "answered": 1}


def test_rate_limited_and_expired() -> None:
    grid, asker = new_grid(), OperatorAsker("cam", SETTINGS.model_copy(update={"answer_timeout_s": 2.0}), tau=0.3)
    for stamp in (0.0, 1.1):
        observe(grid, AHEAD, [0.5, 0.5], stamp)
        asker.update(grid, POSE)
    observe(grid, AHEAD, [0.5, 0.5], 3.5)
    assert asker.update(grid, POSE) is None  # the question expired, and the next is within min_interval_s
    assert asker.counts == {"asked": 1, "expired": 1, "rate_limited": 1}
    observe(grid, AHEAD, [0.5, 0.5], 11.5)
    assert asker.update(grid, POSE) is not None


def test_a_path_replaces_the_heading() -> None:
    xs, ys = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 2.5])
    assert corridor(xs, ys, POSE, 3.0, 1.0).tolist() == [True, False, False]
    assert corridor(xs, ys, POSE, 3.0, 1.0, path=[(0.0, 0.0), (0.0, 5.0)]).tolist() == [False, True, True]


@pytest.mark.parametrize("text", ["maybe", "1.5", "-0.1"])
def test_a_bad_answer_is_refused(text: str) -> None:
    with pytest.raises(ValueError, match="answer"):
        parse_answer(text)
