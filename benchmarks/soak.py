"""Soak test: simulated robots stream JPEGs to several service instances through a router, on loopback.

    python benchmarks/soak.py                          # 8 robots x 15 fps, 640x480, 10 min, 2 instances
    python benchmarks/soak.py --minutes 2 --robots 4   # shorter

Everything runs on this machine (127.0.0.1), is bounded in time and stops by itself. Without --model it
uses random weights of the real CLIPSeg architecture. Reports, per instance, resident memory over time
and, per robot, frames sent / received / processed / dropped / rejected, maps delivered, latency
percentiles (robot stamp to maps received) and the services' errors; writes the same as JSON.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import statistics
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from gcdtrav.client import TraversabilityClient, zenoh_config
from gcdtrav.schemas.images import encode_jpeg
from gcdtrav.service.bench import bench_image, rss_mb
from gcdtrav.service.loopback import SimulatedRobots, free_port, service_processes, wait_for_statuses


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
    args = parser.parse_args()
    deadline_s = args.minutes * 60

    from gcdtrav.service.backends.random_clipseg import save_random_clipseg

    scratch = tempfile.TemporaryDirectory()
    model = args.model
    if model is None:
        print("building random weights of the real architecture ...", file=sys.stderr)
        model = str(save_random_clipseg(Path(scratch.name) / "model", preset="rd64-refined"))
    port = free_port()
    router = zenoh.open(zenoh_config(mode="router", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False))
    common = ["--model", model, "-m", "client", "-e", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"]
    common += ["--threads", str(args.threads), "--no-preview"]
    state = Path(scratch.name)
    arguments = [
        [*common, "--instance", f"soak-{k}", "--state-dir", str(state / f"state{k}")] for k in range(args.instances)
    ]
    stack = contextlib.ExitStack()
    stack.callback(scratch.cleanup)
    stack.callback(router.close)
    services = stack.enter_context(service_processes(arguments))  # stopped first, then the router
    client = TraversabilityClient(
        config=zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False), timeout=5.0
    )
    rss_series: dict[str, list[tuple[float, float]]] = defaultdict(list)
    report: dict[str, Any] = {}
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
        robots.start()
        started = time.monotonic()
        while (elapsed := time.monotonic() - started) < deadline_s:
            time.sleep(min(args.sample_seconds, deadline_s - elapsed))
            for process, k in zip(services, range(args.instances), strict=True):
                rss_series[f"soak-{k}"].append((round(time.monotonic() - started, 1), round(rss_mb(process.pid), 1)))
            sent = sum(robots.sent.values())
            delivered = len(robots.received())
            print(
                f"  t={time.monotonic() - started:6.0f} s  sent {sent}  maps {delivered}  rss "
                + " ".join(f"{name} {series[-1][1]:.0f} MB" for name, series in rss_series.items()),
                file=sys.stderr,
            )
        robots.stop()
        time.sleep(3.0)
        statuses = client.statuses(timeout=5.0)
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
    print(f"written: {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
