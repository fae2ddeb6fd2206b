"""The text of `gcdtrav calibration`, `anchors propose`, `answer` and the status lines, from messages as the
service sends them (the commands against a live service: tests/service/bus/test_experience_e2e.py)."""

from __future__ import annotations

import pytest
from gcdtrav.client.client import ServiceError
from gcdtrav.client.commands.experience import open_question, report_lines, status_lines
from gcdtrav.schemas.experience import (
    AnchorFigures,
    CalibrationFigures,
    CalibrationReport,
    ReliabilityBin,
    answer_score,
)
from gcdtrav.schemas.messages import ExperienceStatus, QuestionStatus, ServiceStatus


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


def test_status_lines_and_the_open_question_an_answer_closes() -> None:
    question = QuestionStatus(id="r1/cam-2", source="r1/cam", stamp=5.0, reason="ambiguous",
                              concepts=["bush", "grass"], region=(1.0, 2.0, 1.5, 2.5))  # fmt: skip
    statuses = [status([], experience=False), status([question])]
    text = "\n".join(status_lines(statuses))
    assert "experience box-1: grid r1/cam, 3 pairs; ask_asked 1, pairs 3" in text
    assert "QUESTION r1/cam-2 (r1/cam): ambiguous ahead, bush vs grass in (1.0, 2.0, 1.5, 2.5)" in text
    assert open_question(statuses, "r1/cam") == "r1/cam-2"
    with pytest.raises(ServiceError, match="no open question for 'r2/cam'"):
        open_question(statuses, "r2/cam")
    assert status_lines([status([], experience=False)]) == []


@pytest.mark.parametrize(("text", "score"), [("drivable", 1.0), ("blocked", 0.0), ("0.25", 0.25), ("1", 1.0)])
def test_answers_read_as_scores(text: str, score: float) -> None:
    assert answer_score(text) == score


@pytest.mark.parametrize("text", ["maybe", "1.5", "-0.1", "nan"])
def test_other_answers_say_what_is_accepted(text: str) -> None:
    with pytest.raises(ValueError, match=r"drivable, blocked or a score|must be in"):
        answer_score(text)
