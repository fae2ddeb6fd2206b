"""Operator commands of `gcdtrav`, torch-free: `gcdtrav status`, `gcdtrav anchors get|set|history|rollback|
propose|apply`, `gcdtrav probe`, and the experience's `gcdtrav calibration` and `gcdtrav answer` (experience.py).

They run from the base install (`pip install gcdtrav`), with the zenoh flags of `gcdtrav serve`.
Exit codes: 0 ok, 1 rejected or failed (one line on stderr), 2 usage error.
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from collections.abc import Callable
from pathlib import Path

import zenoh
from gcdtrav.client.client import AnchorSetRejected, ServiceError, TraversabilityClient
from gcdtrav.client.commands import experience
from gcdtrav.client.commands.density_plot import describe, save_distribution
from gcdtrav.client.commands.grid_status import grid_lines
from gcdtrav.client.session.zenoh_args import add_zenoh_arguments, zenoh_config_from_args
from gcdtrav.schemas.anchors import AnchorSet, AnchorSetError, anchor_diff
from gcdtrav.schemas.messages import (
    AnchorHistoryEntry,
    AnchorHistoryReply,
    ContextDistribution,
    ServiceStatus,
    SourceStatus,
)

COMMANDS = ("status", "anchors", "probe", *experience.COMMANDS)
EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2
RUST_SOURCE = re.compile(r"\s+at \S+\.rs:\d+\.?$")  # zenoh's errors end with the Rust file that raised them


def add_operator_commands(commands: argparse._SubParsersAction) -> None:
    status = commands.add_parser("status", help="instances and sources of the running service (no torch)")
    status.add_argument("--watch", type=float, metavar="SECONDS", help="refresh every SECONDS, with frames/s")
    anchors = commands.add_parser("anchors", help="read or hot-swap the service's anchor set (no torch)")
    actions = anchors.add_subparsers(dest="action", required=True)
    get = actions.add_parser("get", help="print the active anchor set (YAML) or write it to a file")
    get.add_argument("-o", "--output", type=Path, help="write it here (.yaml/.yml or .json)")
    put = actions.add_parser("set", help="validate FILE, show the change, and swap it in on every instance")
    put.add_argument("file", type=Path, help="anchor set, JSON or YAML")
    put.add_argument("--dry-run", action="store_true", help="validate and show the change; swap nothing")
    put.add_argument(
        "--expected",
        metavar="VERSION",
        help="swap only while this set is the active one [the active set the change is shown against]",
    )
    history = actions.add_parser("history", help="the last accepted anchor sets, newest (active) first")
    rollback = actions.add_parser("rollback", help="swap back to an earlier set of the history, on every instance")
    rollback.add_argument("steps", nargs="?", type=positive_int, default=1, help="how far back [1: the set before]")
    propose = actions.add_parser("propose", help="the set fitted on the robot's outcomes, as a diff; --apply swaps it")
    propose.add_argument("--source", help="whose experience [the service's grid]")
    propose.add_argument(
        "--apply", action="store_true", help="swap it in on every instance if judged better (validated, rollback-able)"
    )
    propose.add_argument("--force", action="store_true", help="with --apply: swap it in even if not judged better")
    apply = actions.add_parser(
        "apply", help="swap in a proposal kept by `anchors propose`, by its version: exactly the set reviewed"
    )
    apply.add_argument("version", help="the proposed set's version that `gcdtrav anchors propose` printed")
    apply.add_argument("--force", action="store_true", help="swap it in even if not judged better (marked forced)")
    probe = commands.add_parser("probe", help="a pixel's context distribution, printed or drawn (no torch)")
    probe.add_argument("source", help="the source, e.g. r1/front")
    probe.add_argument("x", type=float, help="image pixel column")
    probe.add_argument("y", type=float, help="image pixel row")
    probe.add_argument("--seq", type=int, help="a kept frame [default: the latest]")
    probe.add_argument("--alpha", type=float, help="CVaR and quantile level, 0 < alpha <= 1 [the service's risk.alpha]")
    probe.add_argument("--tau", type=float, help="P(T < tau) threshold, 0 <= tau <= 1 [the service's risk.tau]")
    probe.add_argument("--png", type=Path, help="also draw the density like the paper's Fig. 2 (needs matplotlib)")
    operator = (status, get, put, history, rollback, propose, apply, probe)
    for parser in (*operator, *experience.add_experience_commands(commands)):
        parser.add_argument("--prefix", default="gcdtrav", help="the service's key prefix [gcdtrav]")
        parser.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for replies [5]")
        add_zenoh_arguments(parser)


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value}: give 1 or more")
    return value


def run(args: argparse.Namespace) -> int:
    """Run an operator command; every failure is one line on stderr."""
    try:
        config = zenoh_config_from_args(args)
        with TraversabilityClient(config=config, prefix=args.prefix, timeout=args.timeout) as client:
            if args.command == "status":
                return watch_status(client, args.watch) if args.watch else print_status(client)
            if args.command == "probe":
                return probe(client, args)
            if args.command in experience.COMMANDS:
                return experience.run_command(client, args)
            actions = {
                "get": get_anchors,
                "set": set_anchors,
                "history": show_history,
                "rollback": roll_back,
                "propose": propose_anchors,
                "apply": apply_proposal,
            }
            return actions[args.action](client, args)
    except AnchorSetError as err:  # the operator's own file (anchors set): the service's refusals are ServiceErrors
        print(f"gcdtrav {args.command}: {one_line(err)}", file=sys.stderr)
        return EXIT_USAGE
    except (AnchorSetRejected, ServiceError, OSError, ValueError) as err:
        print(f"gcdtrav {args.command}: {one_line(err)}", file=sys.stderr)
        return EXIT_FAILED
    except zenoh.ZError as err:  # e.g. an endpoint that cannot be reached in client mode
        print(f"gcdtrav {args.command}: zenoh: {RUST_SOURCE.sub('', one_line(err))}", file=sys.stderr)
        return EXIT_FAILED
    except Exception as err:
        print(f"gcdtrav {args.command}: {type(err).__name__}: {one_line(err)}", file=sys.stderr)
        return EXIT_FAILED


def one_line(err: BaseException) -> str:
    return " ".join(str(err).split())


# ---- status ------------------------------------------------------------------------------------------


INSTANCE_ROW = "{:<{w}}  {:>7}  {:<{mw}}  {:>6}  {:>10}  {:>7}"
SOURCE_ROW = "{:<{w}}  {:<{iw}}  {:>8}  {:>8}  {:>9}  {:>9}  {:>7}  {:>8}  {:>6}  {:>6}  {:>9}  {:>6}  {:>5}  {}"


def status_table(statuses: list[ServiceStatus], fps: Callable[[str, str], str] = lambda i, s: "-") -> str:
    """Instances, then every source that sent anything (also those refused before they took a slot), with its
    drops and rejects by reason and, below, why its last frame gave no maps. Names are never cut: columns are
    as wide as the longest (ROS topics are long)."""
    width = max([len("instance"), *(len(s.instance) for s in statuses)])
    whats = [f"{s.model[-24:]} / {s.anchor_set_version} / {s.method.value} / {s.precision or '-'}" for s in statuses]
    what_header = "model / anchors / method / precision"
    what_width = max([len(what_header), *(len(what) for what in whats)])
    lines = [INSTANCE_ROW.format("instance", "uptime", what_header, "queued", "history MB", "sources",
                                 w=width, mw=what_width)]  # fmt: skip
    for s, what in zip(statuses, whats, strict=True):
        uptime, history = f"{s.uptime_s:.0f}s", f"{s.history_bytes / 1e6:.1f}"
        sources = f"{s.tracked_sources}/{s.max_sources}"
        lines.append(INSTANCE_ROW.format(s.instance, uptime, what, s.queued, history, sources, w=width, mw=what_width))
    rows = [(name, s.instance, src) for s in statuses for name, src in sorted(s.sources.items())]
    name_width = max([len("source"), *(len(name) for name, _, _ in rows)])
    header = ("source", "instance", "frames/s", "received", "processed", "unchanged", "dropped", "rejected", "p50 ms",
              "p99 ms", "clock s", "weight", "share")  # fmt: skip
    lines += ["", SOURCE_ROW.format(*header, "dropped and rejected by reason", w=name_width, iw=width)]
    problems = []
    for name, instance, src in rows:
        p50, p99 = src.latency_ms.get("p50", "-"), src.latency_ms.get("p99", "-")
        weight = "-" if src.weight is None else f"{src.weight:.2f}"
        share = "-" if src.share is None else f"{src.share:.0%}"
        counts = (src.received, src.processed, src.unchanged, src.dropped, src.rejected, p50, p99,
                  clock_offset(src.clock_offset_s), weight, share)  # fmt: skip
        lines.append(
            SOURCE_ROW.format(name, instance, fps(instance, name), *counts, reasons(src), w=name_width, iw=width)
        )
        if src.problem:
            problems.append(f"{name} ({instance}): {src.problem}")
    if problems:
        lines += ["", "why the last frame gave no maps:", *(f"  {line}" for line in problems)]
    lines += grid_lines(statuses)
    lines += fleet_warnings(statuses)
    lines += experience.status_lines(statuses)
    precision = [f"{s.instance}: {s.precision} ({s.precision_reason})" for s in statuses if s.precision_reason]
    if precision:
        lines += ["", *(f"precision {line}" for line in precision)]
    rejected = {reason: n for s in statuses for reason, n in s.rejected_by_reason.items()}
    if rejected:
        lines += ["", "rejected: " + ", ".join(f"{reason} {n}" for reason, n in sorted(rejected.items()))]
    return "\n".join(lines)


def clock_offset(offset_s: float | None) -> str:
    """The source's clock as the service learnt it (service minus robot, plus the link's smallest delay)."""
    if offset_s is None:
        return "-"
    return f"{offset_s:+.2f}" if abs(offset_s) < 1e5 else f"{offset_s:+.3g}"


def reasons(source: SourceStatus) -> str:
    """'stale 3, undecodable 1', and for a source that never took a slot why not: no slot left (max_sources), or
    no frame of it was usable (an undecodable or stale frame is no capacity problem)."""
    counts = {**source.dropped_by_reason, **source.rejected_by_reason}
    text = ", ".join(f"{reason} {n}" for reason, n in sorted(counts.items()))
    if not source.refused:
        return text
    no_slot = any(reason.startswith("too_many_sources") for reason in counts)
    return text + (" (not tracked: no source slot left)" if no_slot else " (not tracked: every frame refused)")


def fleet_warnings(statuses: list[ServiceStatus]) -> list[str]:
    """Unhealthy instances, instances refused for their model, and instances that disagree on the model, the
    anchor set or the precision."""
    lines = [f"UNHEALTHY {s.instance}: {s.reason}" for s in statuses if s.healthy is False]
    lines += [f"TAKES NO SOURCES {s.instance}: {s.model_refused}" for s in statuses if s.model_refused]
    models = {s.instance: s.model_fingerprint for s in statuses if s.model_fingerprint}
    if len(set(models.values())) > 1:
        held = ", ".join(f"{instance} {fingerprint}" for instance, fingerprint in sorted(models.items()))
        lines.append(f"MODELS DIFFER: {held} (checkpoint fingerprints; maps differ between instances)")
    off = {name for s in statuses for name, src in s.sources.items() if abs(src.clock_offset_s or 0.0) > 1.0}
    if off:
        lines.append(
            f"clocks off by more than 1 s: {', '.join(sorted(off))} (served: ages are judged by delay unless "
            "clock: synced; their maps keep their own stamps)"
        )
    versions = {s.instance: s.anchor_set_version for s in statuses}
    if len(set(versions.values())) > 1:
        held = ", ".join(f"{instance} has {version}" for instance, version in sorted(versions.items()))
        lines.append(f"ANCHOR SETS DIFFER: {held} (they converge to the newest accepted set)")
    precisions = {s.precision for s in statuses if s.precision}
    if len(precisions) > 1:
        lines.append(
            "precision differs: "
            + ", ".join(f"{s.instance} {s.precision}" for s in statuses)
            + " (precision: auto measured each machine; set precision explicitly for identical maps)"
        )
    return ["", *lines] if lines else []


def live_statuses(client: TraversabilityClient) -> list[ServiceStatus]:
    statuses = client.statuses()
    if not statuses:
        raise ServiceError(f"no gcdtrav instance answered on '{client.keys.status}': is the service running?")
    return statuses


def print_status(client: TraversabilityClient) -> int:
    print(status_table(live_statuses(client)))
    return EXIT_OK


Counts = dict[tuple[str, str], tuple[float, int]]


def frames_per_s(before: Counts, now: Counts) -> Callable[[str, str], str]:
    """Frames/s of each (instance, source) between two refreshes' processed counts."""

    def fps(instance: str, source: str) -> str:
        old, new = before.get((instance, source)), now[(instance, source)]
        return f"{(new[1] - old[1]) / (new[0] - old[0]):.2f}" if old and new[0] > old[0] else "-"

    return fps


def watch_status(client: TraversabilityClient, every_s: float) -> int:
    """Refresh until Ctrl-C; frames/s from the processed counts between two refreshes."""
    before: Counts = {}
    try:
        while True:
            now, statuses = time.monotonic(), live_statuses(client)
            counts = {(s.instance, n): (now, src.processed) for s in statuses for n, src in s.sources.items()}
            print(f"\x1b[2J\x1b[H{time.strftime('%H:%M:%S')}  gcdtrav status (Ctrl-C stops)\n")
            print(status_table(statuses, frames_per_s(before, counts)), flush=True)
            before = counts
            time.sleep(every_s)
    except KeyboardInterrupt:
        return EXIT_OK


# ---- anchors -----------------------------------------------------------------------------------------


def get_anchors(client: TraversabilityClient, args: argparse.Namespace) -> int:
    active, output = client.anchors().anchor_set, args.output
    if output is None:
        print(f"# active anchor set {active.version}\n{active_yaml(active)}", end="")
    else:
        active.save(output)
        print(f"anchor set {active.version} ({len(active)} anchors) written to {output}")
    return EXIT_OK


def active_yaml(anchors: AnchorSet) -> str:
    import yaml

    return yaml.safe_dump(anchors.model_dump(exclude_none=True), sort_keys=False)


def set_anchors(client: TraversabilityClient, args: argparse.Namespace) -> int:
    new = AnchorSet.load(args.file)  # the same pydantic model the service validates with
    seen = client.anchors()
    active = seen.anchor_set
    changes = anchor_diff(active, new)
    print(f"{active.version} ({len(active)} anchors) -> {new.version} ({len(new)} anchors)")
    print("\n".join(changes) if changes else "no change")
    if args.dry_run:
        print("dry run: nothing swapped")
        return EXIT_OK
    # Only if the set the diff was shown against is still active (1.5 services): of two operators swapping at
    # once one wins, the other gets ActivationLost naming the winner (exit 1, one line).
    expected = args.expected or (seen.version if seen.accepted_at is not None else None)
    version = client.set_anchors(new, expected_version=expected)  # PartialSwap (exit 1) names who holds what
    print(f"swapped: anchor set {version} active on {fleet_sets(client)}")
    return EXIT_OK


def fleet_sets(client: TraversabilityClient) -> str:
    """Which instance holds which anchor set now, e.g. 'box-1 (3f2a...), box-2 (3f2a...)'."""
    statuses = client.statuses()
    return ", ".join(f"{s.instance} ({s.anchor_set_version})" for s in statuses) or "no instance answered"


def show_history(client: TraversabilityClient, args: argparse.Namespace) -> int:
    print("\n".join(history_lines(client.anchor_history())))
    return EXIT_OK


def history_lines(histories: list[AnchorHistoryReply]) -> list[str]:
    """The accepted sets, newest first, once per distinct history (instances sharing the fleet's store answer
    the same one); the set an instance started with (never accepted in the fleet: ``accepted_at`` 0) reads
    'start set', not 1970; a set applied against its verdict is marked FORCED."""
    lines = []
    shared: dict[tuple[tuple[float, str], ...], list[str]] = {}
    for history in histories:
        shared.setdefault(tuple((e.accepted_at, e.version) for e in history.entries), []).append(history.instance)
    shown: set[tuple[tuple[float, str], ...]] = set()
    for history in histories:
        key = tuple((e.accepted_at, e.version) for e in history.entries)
        if key in shown:
            continue
        shown.add(key)
        lines.append(f"instance {', '.join(shared[key])}:")
        lines += [f"  {entry_line(steps, entry)}" for steps, entry in enumerate(history.entries)]
    return lines


def entry_line(steps: int, entry: AnchorHistoryEntry) -> str:
    when = "start set".ljust(19)
    if entry.accepted_at > 0:
        when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(entry.accepted_at))
    label = "active" if steps == 0 else f"rollback {steps}"
    anchors = entry.anchor_set
    line = f"{label:>11}  {when}  {entry.version}  {anchors.name[:30]:<30} {len(anchors):>2} anchors"
    how = " ".join(word for word in (entry.how, f"by {entry.activated_by}" if entry.activated_by else None) if word)
    return line + (f"  {how}" if how else "") + ("  FORCED (against its verdict)" if entry.forced else "")


def roll_back(client: TraversabilityClient, args: argparse.Namespace) -> int:
    """A fleet action: the server's rollback on the instance holding the fleet's newest set; the others adopt."""
    head, reply = client.rollback(args.steps)
    active, target = head.anchor_set, reply.anchor_set
    print(f"{active.version} ({len(active)} anchors) -> {target.version} ({len(target)} anchors)")
    print("\n".join(anchor_diff(active, target)) or "no change")
    print(f"rolled back: anchor set {reply.version} active on {fleet_sets(client)}")
    return EXIT_OK


def propose_anchors(client: TraversabilityClient, args: argparse.Namespace) -> int:
    """The fitted set as a diff with the held-out figures before and after and the verdict; swapped in only with
    --apply, as `anchors set` swaps (validated by every instance, fleet-wide, in the history for a rollback),
    and only if judged better on enough pairs, unless --force."""
    if args.force and not args.apply:
        print("gcdtrav anchors: --force goes with --apply (gcdtrav anchors propose --apply --force)", file=sys.stderr)
        return EXIT_USAGE
    proposal = client.anchor_proposal(args.source)
    print("\n".join(experience.proposal_lines(proposal)))
    refused = experience.refusal(proposal.judged())
    later = f"gcdtrav anchors apply {proposal.proposed_version}" if proposal.kept else "gcdtrav anchors propose --apply"
    forcing = f"not applied: {refused}; {later} --force swaps it in anyway"
    if not args.apply:
        print(forcing if refused else f"not applied: {later} swaps in exactly this set")
        return EXIT_OK
    if refused and not args.force:
        print(f"gcdtrav anchors: {forcing}", file=sys.stderr)
        return EXIT_FAILED
    if proposal.kept:  # the kept proposal: exactly what was shown, while the set it was judged against is active
        version = client.apply_proposal(proposal.proposed_version, force=bool(refused))
    else:  # a service before 1.4 keeps none: the set shown, only over the set shown (if it takes expected)
        version = client.set_anchors(proposal.proposed)
    forced = " (forced)" if refused else ""
    print(f"swapped{forced}: anchor set {version} active on {fleet_sets(client)} (gcdtrav anchors rollback undoes it)")
    return EXIT_OK


def apply_proposal(client: TraversabilityClient, args: argparse.Namespace) -> int:
    """The kept proposal of that version, as reviewed: refused in one line if it is gone, if another set became
    active since it was judged, or (without --force) if it was not judged better."""
    version = client.apply_proposal(args.version, force=args.force)
    print(f"swapped: anchor set {version} active on {fleet_sets(client)} (gcdtrav anchors rollback undoes it)")
    return EXIT_OK


# ---- probe -------------------------------------------------------------------------------------------


def probe(client: TraversabilityClient, args: argparse.Namespace) -> int:
    distribution = client.patch(args.source, args.x, args.y, seq=args.seq, alpha=args.alpha, tau=args.tau)
    print(describe(distribution, (args.x, args.y)))
    if args.png is not None:
        draw_density(distribution, args.png)
        print(f"density drawn to {args.png}")
    return EXIT_OK


def draw_density(d: ContextDistribution, path: Path) -> None:
    """The Gaussian context distribution as in the paper's Fig. 2 (the drawing `gcdtrav infer --figure` uses)."""
    try:
        save_distribution(d, path)
    except ImportError:
        raise ValueError("--png needs matplotlib: pip install matplotlib") from None
