"""The experience's operator commands (docs/calibration.md), torch-free like the rest of operator.py:

  gcdtrav calibration [SOURCE] [--by-source] [--window all|day|hour] [--png FILE]
                                                    the active set graded by the fleet's outcomes
  gcdtrav answer SOURCE [drivable|blocked|SCORE]    show the open question of SOURCE (or --question ID), its
                                                    crop (--save-crop FILE, --show), then answer it

  gcdtrav exclusions [--exclude ROBOT | --include ROBOT] [--reason TEXT] [--operator NAME]
                                                    the robots whose pairs calibration and fits leave out
  gcdtrav kept                                      what the fleet's store keeps: raw pairs per source, sums

and the text both they and `gcdtrav anchors propose` and `gcdtrav status` print.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np
from gcdtrav.client.client import ServiceError, TraversabilityClient
from gcdtrav.schemas.experience import (
    MIN_HELD_OUT_PAIRS,
    AnchorProposal,
    CalibrationFigures,
    CalibrationReport,
    OperatorQuestion,
    ProposalVerdict,
    StoreContents,
    answer_score,
    coverage_shortfall,
)
from gcdtrav.schemas.messages import ServiceStatus, StoreStatus

COMMANDS = ("calibration", "answer", "exclusions", "kept")
FIGURES_ROW = "{:<22} {:>6} {:>7} {:>7} {:>20} {:>6} {:>7} {:>8}"
# `gcdtrav calibration`'s verdict (docs/calibration.md, "For operators"): how far a figure may stray before the
# set is called over- or under-confident.
COVERAGE_SLACK = 0.05  # a q_alpha holding for 0.90 of the outcomes where it promised 0.95 is still fine
ECE_LIMIT = 0.05  # P(T < tau) off by more than 5 points on average
BIAS_LIMIT = 0.1  # T off by more than a tenth of the scale on average


def add_experience_commands(commands: argparse._SubParsersAction) -> list[argparse.ArgumentParser]:
    """The parsers, for operator.py to give the common flags (prefix, timeout, zenoh)."""
    calibration = commands.add_parser("calibration", help="the active anchor set graded by the robot's outcomes")
    calibration.add_argument("source", nargs="?", help="the grid's source [the one the service collects]")
    calibration.add_argument("--png", type=Path, help="also draw the reliability diagram (needs matplotlib)")
    calibration.add_argument("--by-source", action="store_true", help="also each source's (robot's) own figures")
    calibration.add_argument(
        "--window", choices=("all", "day", "hour"), default="all", help="the pairs appended in it [all]"
    )
    answer = commands.add_parser("answer", help="answer the question a service asked about the ground ahead")
    answer.add_argument("source", help="the grid's source the question is about")
    answer.add_argument(
        "answer",
        nargs="?",
        type=answer_argument,
        help="drivable, blocked, or a score in [0, 1] (1 = drivable) [none: show the question]",
    )
    answer.add_argument("--question", help="the question's id [the source's open question]")
    answer.add_argument("--save-crop", type=Path, metavar="FILE", help="first save the question's crop (JPEG) here")
    answer.add_argument("--show", action="store_true", help="first draw the crop in the terminal (24-bit colour)")
    answer.add_argument("--operator", default="", help="who answers (kept with the answer)")
    exclusions = commands.add_parser("exclusions", help="the robots whose pairs calibration and fits leave out")
    which = exclusions.add_mutually_exclusive_group()
    which.add_argument("--exclude", metavar="ROBOT", help="leave ROBOT's pairs out (ROBOT: a source's first chunk)")
    which.add_argument("--include", metavar="ROBOT", help="count ROBOT's pairs again")
    exclusions.add_argument("--reason", default="", help="why (kept with the word)")
    exclusions.add_argument("--operator", default="", help="who asks (kept with the word)")
    kept = commands.add_parser("kept", help="what the fleet's store keeps: raw pairs per source, calibration sums")
    return [calibration, answer, exclusions, kept]


def answer_argument(text: str) -> str:
    """The answer as typed, checked while parsing: a bad one is a usage error (exit 2) before any connection."""
    try:
        answer_score(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return text


def run_command(client: TraversabilityClient, args: argparse.Namespace) -> int:
    if args.command == "calibration":
        return calibration(client, args.source, args.png, args.by_source, args.window)
    if args.command == "exclusions":
        return exclusions(client, args)
    if args.command == "kept":
        print("\n".join(kept_lines(client.kept())))
        return 0
    return answer(client, args)


def exclusions(client: TraversabilityClient, args: argparse.Namespace) -> int:
    robot = args.exclude or args.include
    found = client.exclusions(robot, excluded=args.exclude is not None, actor=args.operator, reason=args.reason)
    for word in found.words:
        state = "excluded" if word.excluded else "included"
        when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(word.at))
        print(f"{word.robot:<16} {state:<9} {when}  by {word.actor or '-'}: {word.reason or '-'}")
    if not found.words:
        print("no robot excluded: every robot's pairs count (each at most experience.max_robot_share)")
    return 0


def experience_source(client: TraversabilityClient) -> str:
    """The grid the service collects outcomes of, from its status."""
    for status in client.statuses():
        if status.experience is not None:
            return status.experience.source
    raise ServiceError("no instance has experience enabled (experience.enabled in the service's settings)")


# ---- calibration ---------------------------------------------------------------------------------------


def calibration(
    client: TraversabilityClient, source: str | None, png: Path | None, by_source: bool = False, window: str = "all"
) -> int:
    report = client.calibration(source or experience_source(client), by_source=by_source, window=window)
    print("\n".join([*report_lines(report), "", *verdict_lines(report.figures)]))
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


def share_lines(shares: dict[str, float], excluded: list[str]) -> list[str]:
    """Each robot's share of the pairs used (capped: experience.max_robot_share) and who is left out."""
    lines = ["share by robot: " + ", ".join(f"{r} {share:.0%}" for r, share in shares.items())] if shares else []
    return lines + ([f"excluded by an operator: {', '.join(excluded)}"] if excluded else [])


def report_lines(report: CalibrationReport) -> list[str]:
    f = report.figures
    kinds = ", ".join(f"{kind} {n}" for kind, n in sorted(report.pairs_by_kind.items())) or "none"
    lines = [
        f"calibration of {report.source}: anchor set {report.anchor_set_version} ({len(report.concepts)} concepts)",
        f"pairs by kind: {kinds}; by anchor-set version: "
        + (", ".join(f"{v} {n}" for v, n in sorted(report.pairs_by_version.items())) or "none"),
        "the fleet's pairs by source: " + (", ".join(f"{s} {n}" for s, n in report.pairs_by_source.items()) or "-"),
        *share_lines(report.share_by_robot, report.excluded_robots),
        "",
        *figures_lines([("active set", f), *sorted((report.by_source or {}).items())]),
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


def reliability_gap(f: CalibrationFigures) -> float | None:
    """Pair-weighted mean of (observed - predicted) P(T < tau) over the bins: > 0, the ground was below tau more
    often than predicted (over-confident); < 0, less often (under-confident). None without pairs."""
    total, gap = 0, 0.0
    for b in f.reliability:
        if b.count and b.observed is not None and b.predicted is not None:
            total, gap = total + b.count, gap + b.count * (b.observed - b.predicted)
    return gap / total if total else None


def calibration_verdict(f: CalibrationFigures) -> tuple[str, list[str], str]:
    """(verdict, the figures behind it, the next step) for `gcdtrav calibration`; docs/calibration.md, "For
    operators". Over-confidence is checked first: it is the one that drives a robot into bad ground."""
    if f.pairs < MIN_HELD_OUT_PAIRS:
        return (
            "too few pairs",
            [f"{f.pairs} pairs, a verdict needs {MIN_HELD_OUT_PAIRS}"],
            "drive on over varied ground, and answer the service's questions (gcdtrav status lists them)",
        )
    shortfall, gap = coverage_shortfall(f), reliability_gap(f)
    over: list[str] = []
    under: list[str] = []
    if shortfall is not None and shortfall > COVERAGE_SLACK:
        kept = {alpha: cover for alpha, cover in f.coverage.items() if cover is not None}
        alpha = min(kept, key=lambda a: kept[a] - (1 - float(a)))
        over.append(f"q_{alpha} held for {kept[alpha]:.2f} of the outcomes, promised {1 - float(alpha):.2f}")
    if f.ece is not None and f.ece > ECE_LIMIT and gap is not None:
        often = "more" if gap > 0 else "less"
        says = f"P(T < {f.tau:g}) off by {f.ece:.2f} (ECE): the ground was below {f.tau:g} {often} often than said"
        (over if gap > 0 else under).append(says)
    if f.bias is not None and abs(f.bias) > BIAS_LIMIT:
        side = "above" if f.bias > 0 else "below"
        (over if f.bias > 0 else under).append(f"T {side} the outcomes by {abs(f.bias):.2f} on average")
    if over:
        return (
            "over-confident",
            over,
            "gcdtrav anchors propose, and --apply it if judged better; until then plan on cvar or p_below, not T",
        )
    if under:
        return (
            "under-confident",
            under,
            "gcdtrav anchors propose, and --apply it if judged better; until then the planner avoids drivable ground",
        )
    return (
        "calibrated",
        [f"MAE {_f(f.mae)}, ECE {_f(f.ece)}, coverage kept"],
        "nothing to change; look again after new terrain, a new anchor set or a new model",
    )


def verdict_lines(f: CalibrationFigures) -> list[str]:
    verdict, because, step = calibration_verdict(f)
    return [f"verdict: {verdict} ({'; '.join(because)})", f"next: {step}"]


def draw_reliability(report: CalibrationReport, path: Path) -> None:
    from gcdtrav.client.commands.calibration_plot import reliability_diagram

    try:
        reliability_diagram(report.figures, path, f"{report.source}: {report.anchor_set_version}")
    except ImportError:
        raise ValueError("--png needs matplotlib: pip install matplotlib") from None


def proposal_lines(proposal: AnchorProposal) -> list[str]:
    """The one text of a proposal, live (`gcdtrav anchors propose`) and offline (`gcdtrav eval --fit-anchors`):
    the +/-/~ diff (as `anchors set --dry-run`), the anchors held near the current set, the figures of both sets
    on the held-out (later) pairs, and the verdict."""
    current, proposed = proposal.current, proposal.proposed
    lines = [f"{current.version} ({len(current)} anchors) -> {proposed.version} ({len(proposed)} anchors)"]
    lines += proposal.diff or ["no change"]
    shrunk = [c.concept for c in proposal.changes if c.shrunk]
    if shrunk:
        lines.append(f"held near the current set (few pairs): {', '.join(shrunk)}")
    verdict = proposal.judged()
    judged_here = " (judged here: the service sent no verdict)" if proposal.verdict is None else ""
    lines += [
        "",
        f"fitted on {proposal.train_pairs} pairs; graded on the {proposal.held_out_pairs} later ones:",
        *share_lines(proposal.share_by_robot, proposal.excluded_robots),
        *figures_lines([("before (current set)", proposal.before), ("after (proposed set)", proposal.after)]),
        "",
        f"verdict: {verdict.reason()}{judged_here}",
    ]
    return lines


def refusal(verdict: ProposalVerdict) -> str | None:
    """Why a proposal should not be applied (for `--apply` to refuse it), or None when it should."""
    if verdict.applicable:
        return None
    why = f"it is {verdict.verdict} on the held-out pairs" if verdict.verdict != "better" else ""
    if not verdict.enough_pairs:
        few = f"only {verdict.held_out_pairs} held-out pairs back it (at least {verdict.min_held_out_pairs})"
        why = f"{why} and {few}" if why else few
    return why


# ---- answers -------------------------------------------------------------------------------------------


def answer(client: TraversabilityClient, args: argparse.Namespace) -> int:
    """Show the question (its region, concepts, crop and the pairs an answer makes) when asked to, or when no
    answer is given, and only then record the answer. Without --question, the open question is the owner's:
    only the instance serving the source answers the question query, and only it takes the answer (another
    instance may still hold one it asked before the source moved)."""
    score = None if args.answer is None else answer_score(args.answer)
    showing = score is None or args.save_crop is not None or args.show
    question = client.question(args.source) if showing or args.question is None else None  # the owner's
    question_id = args.question or (question.id if question is not None else "")
    if showing and question is not None:
        if question.id != question_id:
            raise ServiceError(f"question {question_id} is not open; the open one is {question.id}")
        print("\n".join(question_lines(question)))
        if (args.save_crop is not None or args.show) and not question.crop_jpeg:
            raise ServiceError(f"question {question.id} has no crop (no camera image of its region); nothing recorded")
        if args.save_crop is not None:
            args.save_crop.write_bytes(question.crop_jpeg or b"")
            print(f"crop saved to {args.save_crop}")
        if args.show:
            print("\n".join(crop_ansi(question.crop_jpeg or b"")))
        if score is None:
            print(f"nothing recorded: gcdtrav answer {args.source} drivable|blocked|SCORE answers it")
            return 0
    assert score is not None  # without an answer the question was shown (or ServiceError raised) above
    reply = client.answer(args.source, question_id, score, args.operator)
    print(f"answered {reply.id} ({args.source}): score {reply.score:g}, {reply.pairs} pairs")
    return 0


def question_lines(q: OperatorQuestion) -> list[str]:
    """A question as an operator reads it in a terminal: where, what competes there, what an answer makes."""
    x0, y0, x1, y1 = q.region
    concepts = " vs ".join(f"{c.concept} (at {c.position:.2f}, weight {c.weight:.2f})" for c in q.concepts)
    figures = (("T", q.traversability), ("U", q.uncertainty), ("P(T < tau)", q.p_below), ("match", q.match))
    means = ", ".join(f"{name} {value:.2f}" for name, value in figures if value is not None)
    crop = f"crop {len(q.crop_jpeg)} bytes of JPEG" if q.crop_jpeg else "no crop"
    return [
        f"question {q.id} ({q.source}): {q.reason} ground in x {x0:.1f}..{x1:.1f} m, y {y0:.1f}..{y1:.1f} m "
        f"(the grid's frame), {len(q.cells)} cells; {crop}",
        f"  {concepts}; mean {means or '-'}",
        f"  an answer makes {len(q.cells)} operator pairs, one per cell: drivable (1), blocked (0) or a score",
    ]


def crop_ansi(jpeg: bytes, columns: int = 48) -> list[str]:
    """The crop in a terminal: one character per pixel column and two pixel rows per line (the upper half
    block in the upper pixel's colour on the lower one's), in 24-bit colour."""
    image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise ServiceError("the question's crop is not an image")
    height, width = image.shape[:2]
    cols = min(columns, width)
    rows = max(2, round(height * cols / width / 2) * 2)
    rgb = cv2.resize(image, (cols, rows), interpolation=cv2.INTER_AREA)[:, :, ::-1]
    cell = "\x1b[38;2;{};{};{}m\x1b[48;2;{};{};{}m\u2580"  # foreground: the upper pixel; background: the lower
    return [
        "".join(cell.format(*top, *bottom) for top, bottom in zip(up, down, strict=True)) + "\x1b[0m"
        for up, down in zip(rgb[0::2], rgb[1::2], strict=True)
    ]


def status_lines(statuses: list[ServiceStatus]) -> list[str]:
    """For `gcdtrav status`: each instance's experience, and the open questions."""
    lines = []
    for s in statuses:
        if s.store is not None and not s.store.reachable:
            lines.append(store_line(s.instance, s.store))
        e = s.experience
        if e is None:
            continue
        counts = ", ".join(f"{k} {v}" for k, v in sorted(e.counts.items()) if v)
        lines.append(f"experience {s.instance}: grid {e.source}, {e.pairs} pairs; {counts or 'nothing yet'}")
        for q in e.open_questions:
            region = ", ".join(f"{v:.1f}" for v in q.region)
            makes = f"; an answer makes {q.cells} pairs" if q.cells is not None else ""
            lines.append(
                f"  QUESTION {q.id} ({q.source}): {q.reason} ahead, {' vs '.join(q.concepts)} in ({region}){makes}; "
                f"gcdtrav answer {q.source} drivable|blocked|SCORE (alone: shows it)"
            )
    return ["", *lines] if lines else []


def store_line(instance: str, store: StoreStatus) -> str:
    """A store that cannot be reached, for `gcdtrav status`: since when, what waits, what was dropped."""
    when = store.unreachable_since
    since = time.strftime("%H:%M:%S", time.localtime(when)) if when is not None else "start"
    return (
        f"STORE UNREACHABLE from {instance} since {since}: {store.backend} {store.location}; "
        f"{store.pending_pairs} pairs waiting in memory, {store.dropped_pairs} dropped; {store.error or ''}"
    ).rstrip("; ")


def kept_lines(contents: StoreContents) -> list[str]:
    def when(stamp: float) -> str:
        return time.strftime("%Y-%m-%d %H:%M", time.localtime(stamp)) if stamp > 0 else "before 1.7"

    age = "-" if contents.max_age_days is None else f"{contents.max_age_days:g} days"
    lines = [
        f"store: {contents.backend} {contents.location}",
        f"raw pairs: {contents.pairs:,} of max_pairs {contents.max_pairs:,}; {contents.bytes:,} bytes of max_bytes "
        f"{contents.max_bytes:,}; max_age {age}",
        "",
        f"{'source':<24} {'pairs':>10} {'bytes':>12}  oldest            newest",
    ]
    lines += [f"{k.source[:24]:<24} {k.pairs:>10,} {k.bytes:>12,}  {when(k.oldest):<17} {when(k.newest)}"
              for k in contents.sources]  # fmt: skip
    lines += ["", "calibration sums (kept after the raw pairs go), pairs graded per set@tau:"]
    lines += [f"  {key}: {count:,}" for key, count in contents.graded.items()] or ["  none yet"]
    return lines
