"""The text of `gcdtrav calibration`, `anchors propose`, `answer` and the status lines, from messages as the
service sends them (the commands against a live service: tests/service/bus/test_experience_e2e.py)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from gcdtrav.client.commands.experience import (
    BIAS_LIMIT,
    COVERAGE_SLACK,
    ECE_LIMIT,
    calibration_verdict,
    crop_ansi,
    question_lines,
    report_lines,
    status_lines,
    verdict_lines,
)
from gcdtrav.schemas.experience import (
    MIN_HELD_OUT_PAIRS,
    AnchorFigures,
    CalibrationFigures,
    CalibrationReport,
    OperatorQuestion,
    QuestionConcept,
    ReliabilityBin,
    answer_score,
)
from gcdtrav.schemas.messages import ExperienceStatus, QuestionStatus, ServiceStatus, StoreStatus


def figures(pairs: int) -> CalibrationFigures:
    empty = pairs == 0
    return CalibrationFigures(
        pairs=pairs,
        mae=None if empty else 0.125,
        bias=None if empty else -0.05,
        coverage={"0.05": None if empty else 0.97, "0.1": None if empty else 0.9, "0.2": None if empty else 0.8},
        tau=0.3,
        reliability=[
            ReliabilityBin(
                low=0.0, high=0.1, count=pairs, predicted=None if empty else 0.02, observed=None if empty else 0.05
            )
        ],
        ece=None if empty else 0.03,
        ause=None,
        spearman_u_error=None,
        anchors=[
            AnchorFigures(
                concept="grass",
                position=0.5,
                width=0.0,
                weight_mass=float(pairs),
                dominant_pairs=pairs,
                dominant_mean_outcome=None if empty else 0.8,
            )
        ],
    )


@pytest.mark.parametrize("pairs", [0, 1, 250])
def test_a_report_reads_with_every_figure_or_a_dash(pairs: int) -> None:
    report = CalibrationReport(
        source="r1/cam", stamp=1.0, anchor_set_version="v1", concepts=["grass"], figures=figures(pairs),
        pairs_by_kind={"velocity": pairs} if pairs else {}, counts={"ignored_unknown_cell": 2},
    )  # fmt: skip
    text = "\n".join(report_lines(report))
    assert "calibration of r1/cam: anchor set v1 (1 concepts)" in text
    assert "not paired: ignored_unknown_cell 2" in text
    row = next(line for line in text.splitlines() if line.startswith("active set"))
    if pairs:
        assert row.split()[2:5] == [str(pairs), "0.125", "-0.050"] and "0.97/0.90/0.80" in row
        assert "[0.0, 0.1)  0.02 -> 0.05" in text
    else:
        assert row.split()[2:5] == ["0", "-", "-"] and "predicted -> observed" not in text


def status(questions: list[QuestionStatus], experience: bool = True) -> ServiceStatus:
    return ServiceStatus(
        instance="box-1", uptime_s=1, model="m", anchor_set_version="v1", method="gcd", queued=0, sources={},
        rejected_by_reason={}, last_errors=[],
        experience=ExperienceStatus(source="r1/cam", pairs=3, counts={"pairs": 3, "ask_asked": len(questions)},
                                    open_questions=questions) if experience else None,
    )  # fmt: skip


def test_status_lines_name_the_open_questions() -> None:
    question = QuestionStatus(id="r1/cam-2", source="r1/cam", stamp=5.0, reason="ambiguous",
                              concepts=["bush", "grass"], region=(1.0, 2.0, 1.5, 2.5))  # fmt: skip
    statuses = [status([], experience=False), status([question])]
    text = "\n".join(status_lines(statuses))
    assert "experience box-1: grid r1/cam, 3 pairs; ask_asked 1, pairs 3" in text
    assert "QUESTION r1/cam-2 (r1/cam): ambiguous ahead, bush vs grass in (1.0, 2.0, 1.5, 2.5)" in text
    assert status_lines([status([], experience=False)]) == []


@pytest.mark.parametrize(("text", "score"), [("drivable", 1.0), ("blocked", 0.0), ("0.25", 0.25), ("1", 1.0)])
def test_answers_read_as_scores(text: str, score: float) -> None:
    assert answer_score(text) == score


@pytest.mark.parametrize("text", ["maybe", "1.5", "-0.1", "nan"])
def test_other_answers_say_what_is_accepted(text: str) -> None:
    with pytest.raises(ValueError, match=r"drivable, blocked or a score|must be in"):
        answer_score(text)


# ---- issue 41 item 4: a verdict and the next step; questions shown before they are answered ---------------


def graded(
    pairs: int = 300,
    cover: float = 0.95,
    ece: float = 0.02,
    gap: float = 0.0,
    bias: float = 0.0,
) -> CalibrationFigures:
    """Figures whose q_0.05 covers ``cover`` (the others keep their promise), and whose one filled bin says
    the outcomes fell below tau ``gap`` more often than predicted."""
    f = figures(pairs)
    coverage = {"0.05": cover, "0.1": 0.9, "0.2": 0.8}  # only q_0.05 strays
    bins = [ReliabilityBin(low=0.2, high=0.3, count=pairs, predicted=0.25, observed=0.25 + gap)]
    return f.model_copy(update={"coverage": coverage, "ece": ece, "reliability": bins, "bias": bias})


@pytest.mark.parametrize(
    ("figures_", "verdict", "because"),
    [
        (graded(pairs=MIN_HELD_OUT_PAIRS - 1), "too few pairs", f"{MIN_HELD_OUT_PAIRS - 1} pairs, a verdict needs"),
        (graded(pairs=MIN_HELD_OUT_PAIRS), "calibrated", "coverage kept"),
        (graded(cover=0.95 - COVERAGE_SLACK + 0.001), "calibrated", "coverage kept"),  # just within the slack
        (
            graded(cover=0.95 - COVERAGE_SLACK - 0.01),
            "over-confident",
            "held for 0.89 of the outcomes, promised 0.95",
        ),
        (graded(ece=ECE_LIMIT), "calibrated", "coverage kept"),
        (graded(ece=0.2, gap=0.2), "over-confident", "the ground was below 0.3 more often than said"),
        (graded(ece=0.2, gap=-0.2), "under-confident", "the ground was below 0.3 less often than said"),
        (graded(bias=BIAS_LIMIT + 0.01), "over-confident", "T above the outcomes by 0.11 on average"),
        (graded(bias=-BIAS_LIMIT - 0.01), "under-confident", "T below the outcomes by 0.11 on average"),
        (graded(cover=0.5, ece=0.2, gap=-0.2), "over-confident", "held for 0.50 of the"),  # the unsafe side wins
    ],
)
def test_the_calibration_verdict_names_its_figures_and_the_next_step(
    figures_: CalibrationFigures, verdict: str, because: str
) -> None:
    said, reasons, step = calibration_verdict(figures_)
    assert said == verdict and because in "; ".join(reasons)
    lines = verdict_lines(figures_)
    assert lines[0].startswith(f"verdict: {verdict} (") and lines[1].startswith("next: ")
    assert ("gcdtrav anchors propose" in step) == (verdict in ("over-confident", "under-confident"))


def question(crop: bytes | None) -> OperatorQuestion:
    return OperatorQuestion(
        id="r1/cam-2", source="r1/cam", stamp=5.0, reason="ambiguous", region=(1.0, 2.0, 1.5, 2.5),
        cells=[(1.05, 2.05), (1.15, 2.05), (1.25, 2.05)], anchor_set_version="v1", crop_jpeg=crop,
        concepts=[QuestionConcept(concept="bush", position=0.45, weight=0.52),
                  QuestionConcept(concept="grass", position=0.5, weight=0.31)],
        traversability=0.47, uncertainty=0.21, p_below=0.4, match=None,
    )  # fmt: skip


def test_a_question_reads_in_a_terminal_with_the_pairs_an_answer_makes() -> None:
    image = np.zeros((40, 60, 3), np.uint8)
    image[:20] = (255, 0, 0)  # BGR: blue above, black below
    jpeg = cv2.imencode(".jpg", image)[1].tobytes()
    lines = question_lines(question(jpeg))
    assert lines[0] == (
        f"question r1/cam-2 (r1/cam): ambiguous ground in x 1.0..1.5 m, y 2.0..2.5 m (the grid's frame), 3 cells; "
        f"crop {len(jpeg)} bytes of JPEG"
    )
    assert (
        lines[1]
        == "  bush (at 0.45, weight 0.52) vs grass (at 0.50, weight 0.31); mean T 0.47, U 0.21, P(T < tau) 0.40"
    )
    assert "an answer makes 3 operator pairs" in lines[2]
    drawn = crop_ansi(jpeg, columns=30)
    assert len(drawn) == 10 and all(line.count("\u2580") == 30 and line.endswith("\x1b[0m") for line in drawn)
    assert drawn[0].startswith("\x1b[38;2;0;0;25") and drawn[-1].startswith("\x1b[38;2;0;0;0m")  # RGB: blue, black
    assert "no crop" in question_lines(question(None))[0]


def test_the_status_line_says_how_many_pairs_an_answer_makes() -> None:
    listed = QuestionStatus(id="r1/cam-2", source="r1/cam", stamp=5.0, reason="ambiguous",
                            concepts=["bush", "grass"], region=(1.0, 2.0, 1.5, 2.5), cells=12)  # fmt: skip
    assert "in (1.0, 2.0, 1.5, 2.5); an answer makes 12 pairs; gcdtrav answer r1/cam" in "\n".join(
        status_lines([status([listed])])
    )


def test_an_unreachable_store_is_a_status_line_and_a_reachable_one_none() -> None:
    down = StoreStatus(backend="postgresql", location="postgresql://gcdtrav@db:5432/gcdtrav", reachable=False,
                       unreachable_since=1.7e9, error="refused", pending_pairs=40, dropped_pairs=3)  # fmt: skip
    text = "\n".join(status_lines([status([]).model_copy(update={"store": down})]))
    assert "STORE UNREACHABLE from box-1 since " in text and "postgresql postgresql://gcdtrav@db:5432/gcdtrav" in text
    assert "40 pairs waiting in memory, 3 dropped; refused" in text
    up = down.model_copy(update={"reachable": True, "unreachable_since": None, "error": None})
    assert "STORE" not in "\n".join(status_lines([status([]).model_copy(update={"store": up})]))


def test_a_report_names_its_sources_and_their_own_figures() -> None:
    report = CalibrationReport(
        source="r1/cam", stamp=1.0, anchor_set_version="v1", concepts=["grass"], figures=figures(250),
        pairs_by_source={"r1/cam": 200, "r2/cam": 50}, by_source={"r1/cam": figures(200), "r2/cam": figures(50)},
    )  # fmt: skip
    text = "\n".join(report_lines(report))
    assert "the fleet's pairs by source: r1/cam 200, r2/cam 50" in text
    rows = [line.split()[:2] for line in text.splitlines() if line.startswith(("r1/cam ", "r2/cam "))]
    assert rows == [["r1/cam", "200"], ["r2/cam", "50"]]
