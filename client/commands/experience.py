"""The experience's operator commands (docs/calibration.md), torch-free like the rest of operator.py:

  gcdtrav calibration [SOURCE] [--png FILE]         the active set graded by the robot's outcomes
  gcdtrav answer SOURCE drivable|blocked|SCORE      answer the open question of SOURCE (or --question ID)

and the text both they and `gcdtrav anchors propose` and `gcdtrav status` print.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from gcdtrav.client.client import ServiceError, TraversabilityClient
from gcdtrav.schemas.experience import AnchorProposal, CalibrationFigures, CalibrationReport, answer_score
from gcdtrav.schemas.messages import ServiceStatus

COMMANDS = ("calibration", "answer")
FIGURES_ROW = "{:<22} {:>6} {:>7} {:>7} {:>20} {:>6} {:>7} {:>8}"


def add_experience_commands(commands: argparse._SubParsersAction) -> list[argparse.ArgumentParser]:
    """The parsers, for operator.py to give the common flags (prefix, timeout, zenoh)."""
    calibration = commands.add_parser("calibration", help="the active anchor set graded by the robot's outcomes")
    calibration.add_argument("source", nargs="?", help="the grid's source [the one the service collects]")
    calibration.add_argument("--png", type=Path, help="also draw the reliability diagram (needs matplotlib)")
    answer = commands.add_parser("answer", help="answer the question a service asked about the ground ahead")
    answer.add_argument("source", help="the grid's source the question is about")
    answer.add_argument("answer", type=answer_argument, help="drivable, blocked, or a score in [0, 1] (1 = drivable)")
    answer.add_argument("--question", help="the question's id [the source's open question]")
    answer.add_argument("--operator", default="", help="who answers (kept with the answer)")
    return [calibration, answer]


def answer_argument(text: str) -> str:
    """The answer as typed, checked while parsing: a bad one is a usage error (exit 2) before any connection."""
    try:
        answer_score(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return text


def run_command(client: TraversabilityClient, args: argparse.Namespace) -> int:
    if args.command == "calibration":
        return calibration(client, args.source, args.png)
    return answer(client, args.source, args.answer, args.question, args.operator)


def experience_source(client: TraversabilityClient) -> str:
    """The grid the service collects outcomes of, from its status."""
    for status in client.statuses():
        if status.experience is not None:
            return status.experience.source
    raise ServiceError("no instance has experience enabled (experience.enabled in the service's settings)")


# ---- calibration ---------------------------------------------------------------------------------------


def calibration(client: TraversabilityClient, source: str | None, png: Path | None) -> int:
    report = client.calibration(source or experience_source(client))
    print("\n".join(report_lines(report)))
    if png is not None:
        draw_reliability(report, png)
        print(f"reliability diagram drawn to {png}")
    return 0


def _f(value: float | None, digits: int = 3) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def figures_lines(rows: list[tuple[str, CalibrationFigures]]) -> list[str]:
    """One row per (label, figures): pairs, MAE, bias, coverage of q_0.05 / q_0.1 / q_0.2, ECE, AUSE, rho."""
    header = ("", "pairs", "MAE", "bias", "cover q.05/q.1/q.2", "ECE", "AUSE", "Spearman")
    lines = [FIGURES_ROW.format(*header)]
    for label, f in rows:
        cover = "/".join(_f(f.coverage.get(alpha), 2) for alpha in ("0.05", "0.1", "0.2"))
        lines.append(
            FIGURES_ROW.format(
                label, f.pairs, _f(f.mae), _f(f.bias), cover, _f(f.ece), _f(f.ause, 4), _f(f.spearman_u_error)
            )
        )
    return lines


def report_lines(report: CalibrationReport) -> list[str]:
    f = report.figures
    kinds = ", ".join(f"{kind} {n}" for kind, n in sorted(report.pairs_by_kind.items())) or "none"
    lines = [
        f"calibration of {report.source}: anchor set {report.anchor_set_version} ({len(report.concepts)} concepts)",
        f"pairs by kind: {kinds}; by anchor-set version: "
        + (", ".join(f"{v} {n}" for v, n in sorted(report.pairs_by_version.items())) or "none"),
        "",
        *figures_lines([("active set", f)]),
        "",
        f"{'anchor':<16} {'position':>8} {'width':>6} {'weight':>8} {'dominant':>8} {'mean outcome':>12}",
    ]
    for a in f.anchors:
        lines.append(
            f"{a.concept[:16]:<16} {a.position:>8.3f} {a.width:>6.3f} {a.weight_mass:>8.1f} {a.dominant_pairs:>8} "
            f"{_f(a.dominant_mean_outcome):>12}"
        )
    filled = [b for b in f.reliability if b.count]
    if filled:
        lines += ["", f"P(T < {f.tau:g}) predicted -> observed (pairs):"]
        lines += [f"  [{b.low:.1f}, {b.high:.1f})  {_f(b.predicted, 2)} -> {_f(b.observed, 2)}  ({b.count})"
                  for b in filled]  # fmt: skip
    ignored = {k: v for k, v in sorted(report.counts.items()) if k.startswith(("ignored_", "rejected_"))}
    if ignored:
        lines += ["", "not paired: " + ", ".join(f"{k} {v}" for k, v in ignored.items())]
    return lines


def draw_reliability(report: CalibrationReport, path: Path) -> None:
    from gcdtrav.client.commands.calibration_plot import reliability_diagram

    try:
        reliability_diagram(report.figures, path, f"{report.source}: {report.anchor_set_version}")
    except ImportError:
        raise ValueError("--png needs matplotlib: pip install matplotlib") from None


def proposal_lines(proposal: AnchorProposal) -> list[str]:
    """The +/-/~ diff (as `anchors set --dry-run`), the anchors held near the current set, the figures of both
    sets on the held-out (later) pairs."""
    current, proposed = proposal.current, proposal.proposed
    lines = [f"{current.version} ({len(current)} anchors) -> {proposed.version} ({len(proposed)} anchors)"]
    lines += proposal.diff or ["no change"]
    shrunk = [c.concept for c in proposal.changes if c.shrunk]
    if shrunk:
        lines.append(f"held near the current set (few pairs): {', '.join(shrunk)}")
    lines += [
        "",
        f"fitted on {proposal.train_pairs} pairs; graded on the {proposal.held_out_pairs} later ones:",
        *figures_lines([("before (current set)", proposal.before), ("after (proposed set)", proposal.after)]),
    ]
    return lines


# ---- answers -------------------------------------------------------------------------------------------


def open_question(statuses: list[ServiceStatus], source: str) -> str:
    for status in statuses:
        for question in status.experience.open_questions if status.experience else []:
            if question.source == source:
                return question.id
    raise ServiceError(f"no open question for '{source}' (gcdtrav status lists them)")


def answer(client: TraversabilityClient, source: str, text: str, question: str | None, operator: str) -> int:
    score = answer_score(text)
    question_id = question or open_question(client.statuses(), source)
    reply = client.answer(source, question_id, score, operator)
    print(f"answered {reply.id} ({source}): score {reply.score:g}, {reply.pairs} pairs")
    return 0


def status_lines(statuses: list[ServiceStatus]) -> list[str]:
    """For `gcdtrav status`: each instance's experience, and the open questions."""
    lines = []
    for s in statuses:
        e = s.experience
        if e is None:
            continue
        counts = ", ".join(f"{k} {v}" for k, v in sorted(e.counts.items()) if v)
        lines.append(f"experience {s.instance}: grid {e.source}, {e.pairs} pairs; {counts or 'nothing yet'}")
        for q in e.open_questions:
            region = ", ".join(f"{v:.1f}" for v in q.region)
            lines.append(
                f"  QUESTION {q.id} ({q.source}): {q.reason} ahead, {' vs '.join(q.concepts)} in ({region}); "
                f"gcdtrav answer {q.source} drivable|blocked|SCORE"
            )
    return ["", *lines] if lines else []
