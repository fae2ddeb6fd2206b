"""Soak test: simulated robots stream JPEGs to several service instances through a router, on loopback.

    python -m benchmarks.soak                          # 8 robots x 15 fps, 640x480, 10 min, 2 instances
    python -m benchmarks.soak --minutes 2 --robots 4   # shorter
    python -m benchmarks.soak --churn 2 --sample-seconds 30   # + 2 frames/s, each under a new source name

Everything runs on this machine (127.0.0.1), is bounded in time and stops by itself. Without --model it
uses random weights of the real CLIPSeg architecture. Reports, per instance, resident memory over time
and, per robot, frames sent / received / processed / dropped / rejected, maps delivered, latency
percentiles (robot stamp to maps received) and the services' errors; writes the same as JSON.

With --churn, sources come and go as well: every churn frame carries a new source name (a robot that
puts a frame counter in its key, or a hostile peer). Resident memory must level off within the bound that
the settings give (docs/architecture.md, Memory), and the steady robots must still be served evenly; the
report adds each instance's tracked sources, history and pending bytes at every sample, and the verdict.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import statistics
import sys
import tempfile
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from gcdtrav.client import ServiceError, TraversabilityClient, zenoh_config
from gcdtrav.schemas.images import encode_jpeg
from gcdtrav.schemas.messages import ServiceStatus
from gcdtrav.service.commands.bench import bench_image, rss_mb

from tools.loopback import (
    INFER_EVERY_FRAME,
    SimulatedRobots,
    free_port,
    service_processes,
    wait_for_statuses,
    waits_before_dropping,
)


class ChurningSources:
    """One thread publishing ``fps`` frames/s, each under a source name never used before."""

    def __init__(self, client: TraversabilityClient, fps: float, jpeg: bytes) -> None:
        self.client, self.fps, self.jpeg, self.sent = client, fps, jpeg, 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        next_at = time.monotonic()
        while not self._stop.is_set():
            # A plain put of the JPEG: a declared publisher per name would grow this process instead.
            key = f"{self.client.input_prefix}/churn/frame_{self.sent:06d}"
            self.client.session.put(key, self.jpeg, encoding=zenoh.Encoding.IMAGE_JPEG)
            self.sent += 1
            next_at += 1.0 / self.fps
            self._stop.wait(max(0.0, next_at - time.monotonic()))

    def start(self) -> None:
        if self.fps > 0:
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5)


def sample_bounds(
    client: TraversabilityClient, at: float, churn_sent: int, series: dict[str, list[dict[str, float]]]
) -> None:
    """Each instance's tracked sources, history and pending bytes, as its status reports them."""
    try:
        statuses = client.statuses(timeout=5.0)
    except ServiceError as err:
        print(f"  status query failed: {err}", file=sys.stderr)
        return
    for status in statuses:
        series[status.instance].append(
            {
                "t": at,
                "churn_sent": churn_sent,
                "tracked_sources": status.tracked_sources,
                "history_mb": round(status.history_bytes / 1e6, 1),
                "queued_mb": round(status.queued_bytes / 1e6, 1),
                "too_many_sources": status.rejected_by_reason.get("too_many_sources", 0),
            }
        )


def churn_verdict(
    args: argparse.Namespace,
    churn_sent: int,
    per_robot: dict[str, dict[str, Any]],
    rss: dict[str, list[tuple[float, float]]],
    bounds: dict[str, list[dict[str, float]]],
) -> dict[str, Any]:
    """Did memory level off within the settings' bound, and were the steady robots served evenly?"""
    # The bound the settings give (docs/architecture.md, Memory): the serving service (its RSS at the first
    # sample after frames began, less the history and pending bytes it held then: model, torch, zenoh and
    # one frame's working set) plus the history and pending budgets. Levelled: the last third's peak stays
    # within the bound and no more than 5 % above the middle third's.
    memory = {}
    for name, series in rss.items():
        values = [v for _, v in series]
        first = (bounds.get(name) or [{"history_mb": 0.0, "queued_mb": 0.0}])[0]
        serving = values[1 if len(values) > 1 else 0] - first["history_mb"] - first["queued_mb"]
        bound = serving + args.history_budget_mb + args.pending_budget_mb
        third = max(len(values) // 3, 1)
        middle = values[third : 2 * third] or values
        memory[name] = {
            "loaded_mb": values[0],
            "serving_mb": round(serving, 1),
            "bound_mb": round(bound, 1),
            "peak_mb": max(values),
            "middle_third_peak_mb": max(middle),
            "last_third_peak_mb": max(values[-third:]),
            "within_bound": max(values) <= bound,
            "levelled": max(values[-third:]) <= min(bound, 1.05 * max(middle)),
        }
    maps = [c["maps_delivered"] for c in per_robot.values()]
    # Evenness that does not depend on the host's speed: the share of the frames the service took in (received,
    # not refused) that came back as maps. A fair scheduler serves the same share of each steady robot's
    # frames (all of them on a fast box, fewer of each on a slow one), whatever each robot's thread managed to
    # send and however late a robot took its slot; counts over wall time differ by both.
    served = [c["maps_delivered"] / max(c["received"] - c["rejected"], 1) for c in per_robot.values()]
    refused = sum(series[-1]["too_many_sources"] for series in bounds.values() if series)
    return {
        "churn_frames_sent": churn_sent,
        "churn_frames_refused_too_many_sources": refused,
        "rss": memory,
        "bounds": bounds,
        "max_tracked_sources": max((b["tracked_sources"] for s in bounds.values() for b in s), default=0),
        "max_history_mb": max((b["history_mb"] for s in bounds.values() for b in s), default=0),
        "steady_maps_min_max": [min(maps, default=0), max(maps, default=0)],
        "steady_served_min_max": [round(min(served, default=0), 3), round(max(served, default=0), 3)],
    }


def all_counted(sent: dict[str, int], statuses: list[ServiceStatus]) -> bool:
    """Every robot's frames sent are counted received by the instances that answered."""
    received = {name: sum(s.sources[name].received for s in statuses if name in s.sources) for name in sent}
    return all(received[name] >= count for name, count in sent.items())


def with_last_seen(
    statuses: list[ServiceStatus], names: list[str], seen: dict[tuple[str, str], Any]
) -> list[ServiceStatus]:
    """The statuses with each robot's counts as last seen by its instance (kept in ``seen``): an instance that
    forgot an idle robot no longer reports them."""
    kept = []
    for status in statuses:
        sources = dict(status.sources)
        for name in names:
            if name in sources:
                seen[(status.instance, name)] = sources[name]
            elif (status.instance, name) in seen:
                sources[name] = seen[(status.instance, name)]
        kept.append(status.model_copy(update={"sources": sources}))
    return kept


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--robots", type=int, default=8)
    parser.add_argument("--fps", type=float, default=15.0)
    parser.add_argument("--instances", type=int, default=2)
    parser.add_argument("--model", default=None, help="checkpoint directory [random weights, real architecture]")
    parser.add_argument("--threads", type=int, default=1, help="torch threads per instance [1]")
    parser.add_argument("--sample-seconds", type=float, default=10.0)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/soak.json"))
    parser.add_argument("--churn", type=float, default=0.0, help="frames/s, each under a new source name [0]")
    parser.add_argument("--max-sources", type=int, default=256, help="the services' max_sources [256]")
    parser.add_argument("--source-idle-s", type=float, default=300.0, help="the services' source_idle_s [300]")
    parser.add_argument("--history-budget-mb", type=float, default=512.0, help="history_budget_mb [512]")
    parser.add_argument("--pending-budget-mb", type=float, default=256.0, help="pending_budget_mb [256]")
    args = parser.parse_args()
    deadline_s = args.minutes * 60

    from tools.random_clipseg import checkpoint_or_random

    scratch = tempfile.TemporaryDirectory()
    model = str(checkpoint_or_random(args.model, Path(scratch.name)))
    port = free_port()
    # The router and the robots stand in for other machines: on this loaded box they wait for their sending
    # thread instead of dropping (waits_before_dropping); the services keep the product's settings.
    router = zenoh.open(
        waits_before_dropping(zenoh_config(mode="router", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False))
    )
    common = ["--model", model, "-m", "client", "-e", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"]
    common += ["--threads", str(args.threads), "--no-preview"]
    state = Path(scratch.name)
    settings = state / "bounds.yaml"
    # The churn comes from one client session: no per-publisher cap, so that it measures the source cap.
    settings.write_text(
        f"max_sources: {args.max_sources}\nsource_idle_s: {args.source_idle_s}\nmax_sources_per_publisher: null\n"
        f"history_budget_mb: {args.history_budget_mb}\npending_budget_mb: {args.pending_budget_mb}\n"
        + INFER_EVERY_FRAME
    )
    common += ["--settings", str(settings)]
    arguments = [
        [*common, "--instance", f"soak-{k}", "--state-dir", str(state / f"state{k}")] for k in range(args.instances)
    ]
    stack = contextlib.ExitStack()
    stack.callback(scratch.cleanup)
    stack.callback(router.close)
    services = stack.enter_context(service_processes(arguments))  # stopped first, then the router
    robots_config = zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    client = TraversabilityClient(config=waits_before_dropping(robots_config), timeout=5.0)
    rss_series: dict[str, list[tuple[float, float]]] = defaultdict(list)
    bounds_series: dict[str, list[dict[str, float]]] = defaultdict(list)
    report: dict[str, Any] = {}
    churn = ChurningSources(client, args.churn, encode_jpeg(bench_image(480, 640, seed=1), 85))
    try:
        wait_for_statuses(client, args.instances)
        names = [f"robot{i}/front" for i in range(args.robots)]
        robots = SimulatedRobots(client, names, args.fps, encode_jpeg(bench_image(480, 640), 85))
        subscriber = client.subscribe_maps("**", robots.on_maps)
        time.sleep(0.5)
        print(
            f"soak: {args.robots} robots x {args.fps:g} fps, 640x480 JPEG, {args.instances} instances, "
            f"{args.minutes:g} min",
            file=sys.stderr,
        )
        for process, k in zip(services, range(args.instances), strict=True):  # loaded, before any frame
            rss_series[f"soak-{k}"].append((0.0, round(rss_mb(process.pid), 1)))
        robots.start()
        churn.start()
        started = time.monotonic()
        while (elapsed := time.monotonic() - started) < deadline_s:
            time.sleep(min(args.sample_seconds, deadline_s - elapsed))
            for process, k in zip(services, range(args.instances), strict=True):
                rss_series[f"soak-{k}"].append((round(time.monotonic() - started, 1), round(rss_mb(process.pid), 1)))
            if args.churn:
                sample_bounds(client, round(time.monotonic() - started, 1), churn.sent, bounds_series)
            sent = sum(robots.sent.values())
            delivered = len(robots.received())
            print(
                f"  t={time.monotonic() - started:6.0f} s  sent {sent}  churn {churn.sent}  maps {delivered}  rss "
                + " ".join(f"{name} {series[-1][1]:.0f} MB" for name, series in rss_series.items()),
                file=sys.stderr,
            )
        robots.stop()
        churn.stop()
        # Let the last frames finish: until every frame sent is counted received somewhere (a loaded host may
        # count the last one seconds late). The services forget a stopped robot source_idle_s after its last
        # frame: its counts are kept as last seen. The bound only ends a wait for a frame that is lost.
        settle_until = time.monotonic() + 60.0
        seen: dict[tuple[str, str], Any] = {}
        statuses = with_last_seen(client.statuses(timeout=5.0), robots.names, seen)
        while not all_counted(robots.sent, statuses) and time.monotonic() < settle_until:
            time.sleep(0.2)
            statuses = with_last_seen(client.statuses(timeout=5.0), robots.names, seen)
        subscriber.undeclare()
        per_robot = {}
        for name in robots.names:
            counts = {"sent": robots.sent[name], "received": 0, "processed": 0, "dropped": 0, "rejected": 0}
            for status in statuses:
                source = status.sources.get(name)
                if source is not None:
                    for key in ("received", "processed", "dropped", "rejected"):
                        counts[key] += getattr(source, key)
            arrivals = robots.received(name)
            latencies = [a.latency_ms for a in arrivals]
            counts["maps_delivered"] = len(arrivals)
            counts["instances"] = sorted({a.instance for a in arrivals})
            counts["latency_ms"] = (
                {f"p{q}": round(float(np.percentile(latencies, q)), 1) for q in (50, 90, 99)} if latencies else {}
            )
            per_robot[name] = counts
        all_latency = [a.latency_ms for a in robots.received()]
        report = {
            "settings": vars(args) | {"out": str(args.out)},
            "per_robot": per_robot,
            "latency_ms_all": {f"p{q}": round(float(np.percentile(all_latency, q)), 1) for q in (50, 90, 99)}
            if all_latency
            else {},
            "rss_mb": dict(rss_series),
            "rss_growth_mb": {name: round(series[-1][1] - series[0][1], 1) for name, series in rss_series.items()},
            "errors": {status.instance: status.rejected_by_reason for status in statuses},
            "last_errors": {status.instance: status.last_errors for status in statuses},
            "lost": sum(c["sent"] - c["received"] for c in per_robot.values()),
        }
        if args.churn:
            report["churn"] = churn_verdict(args, churn.sent, per_robot, dict(rss_series), dict(bounds_series))
    finally:
        client.close()
        stack.close()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print("| robot | sent | received | processed | dropped | rejected | maps | instance | p50 ms | p99 ms |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, c in report["per_robot"].items():
        print(
            f"| {name} | {c['sent']} | {c['received']} | {c['processed']} | {c['dropped']} | {c['rejected']} | "
            f"{c['maps_delivered']} | {','.join(c['instances'])} | {c['latency_ms'].get('p50', '-')} | "
            f"{c['latency_ms'].get('p99', '-')} |"
        )
    print(f"latency all robots: {report['latency_ms_all']}")
    for name, series in report["rss_mb"].items():
        values = [v for _, v in series]
        print(
            f"{name}: RSS {min(values):.0f}..{max(values):.0f} MB (median {statistics.median(values):.0f}), "
            f"growth first->last {report['rss_growth_mb'][name]:+.1f} MB over {len(values)} samples"
        )
    print(f"errors: {report['errors']}; sent but never received by a service: {report['lost']}")
    if "churn" in report:
        print(f"churn: {json.dumps(report['churn'])}")
    print(f"written: {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
