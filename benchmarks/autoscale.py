"""Autoscaling on loopback (issue 43): does the fleet scale on its map age without robots noticing?

A zenoh router on 127.0.0.1, `gcdtrav serve` instances started and stopped (SIGTERM) as a cluster would, a real
Prometheus (Debian's /usr/bin/prometheus) scraping each instance's /metrics every second, and a controller
loop applying the HPA formula of deploy/kubernetes to what Prometheus answers:

    busy    = sum(rate(gcdtrav_inference_seconds_sum[W])) / current   (--signal busy, the manifests' signal)
    age     = histogram_quantile(0.95, sum by (le) (rate(gcdtrav_map_age_seconds_bucket[W])))   (--signal age)
    desired = ceil(current x metric / target)   (within 10 % of the target: no change; HPA's tolerance)

clamped to [min, max]; up at once but at most +2 per 20 s, down by one instance per 10 s and only to the highest
recommendation of the last --down-window s (HPA's scale-down stabilisation): deploy/kubernetes's behaviour (+4 per
60 s, -1 per 60 s, 300 s) at a benchmark's time scale. Robots ramp 2 -> 8 -> 2 at --fps.

TEST BACKEND: every instance runs tools/faulty_serve.py with FAULTY_SERVE_FRAME_COST_S (--frame-cost): each
inference takes that long, slept, on a tiny random model, so one instance serves 1/cost frames/s and capacity
grows with instances even on a 2-core machine. The numbers say how the scaling behaves, not how fast gcdtrav
is. Per phase: instances, map age p50/p95 as the robots saw it (receipt minus capture stamp), the longest gap
any robot saw around each scale event, stale maps (older than max_frame_age_s: none allowed), whether the
count settled without flapping.

    python -m benchmarks.autoscale [--quick] [--out benchmarks/autoscale-DATE.json]
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import platform
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import urllib.parse
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh
from gcdtrav.client import TraversabilityClient, zenoh_config
from gcdtrav.schemas.images import encode_jpeg
from gcdtrav.service.commands.bench import bench_image

from tools.loopback import INFER_EVERY_FRAME, SimulatedRobots, free_port

MAX_FRAME_AGE_S = 5.0
SETTLED_S = 30.0  # a phase settled if the count did not change in its last this many seconds
QUERIES = {
    "busy": "sum(rate(gcdtrav_inference_seconds_sum[{window}s]))",  # divided by the instances: per instance
    "age": "histogram_quantile(0.95, sum by (le) (rate(gcdtrav_map_age_seconds_bucket[{window}s])))",
}
TARGETS = {"busy": 0.7, "age": 0.8}


@dataclass
class Event:
    at: float  # time.monotonic()
    kind: str  # "up" or "down"
    instance: str
    instances_after: int


@dataclass
class Fleet:
    """The router (in this process), Prometheus, and the instances, each with its metrics port."""

    model: str
    scratch: Path
    frame_cost_s: float
    port: int = field(default_factory=free_port)
    prometheus_port: int = field(default_factory=free_port)
    processes: dict[str, tuple[subprocess.Popen[str], int]] = field(default_factory=dict)
    started: int = 0

    def __post_init__(self) -> None:
        listen = [f"tcp/127.0.0.1:{self.port}"]
        self.router = zenoh.open(zenoh_config(mode="router", listen=listen, multicast_scouting=False))
        self.settings = self.scratch / "autoscale.yaml"
        self.settings.write_text(f"max_frame_age_s: {MAX_FRAME_AGE_S}\nprecision: fp32\n{INFER_EVERY_FRAME}")
        self.targets = self.scratch / "targets.json"
        self._write_targets()
        config = self.scratch / "prometheus.yml"
        config.write_text(
            "global: {scrape_interval: 1s, evaluation_interval: 1s}\n"
            "scrape_configs:\n"
            "  - job_name: gcdtrav\n"
            f"    file_sd_configs: [{{files: ['{self.targets}'], refresh_interval: 1s}}]\n"
        )
        prometheus = shutil.which("prometheus")
        if prometheus is None:
            raise SystemExit("the prometheus binary is needed: apt-get install prometheus")
        self.prometheus = subprocess.Popen(
            [
                prometheus,
                f"--config.file={config}",
                f"--storage.tsdb.path={self.scratch / 'tsdb'}",
                f"--web.listen-address=127.0.0.1:{self.prometheus_port}",
            ],
            stdout=subprocess.DEVNULL,
            stderr=(self.scratch / "prometheus.log").open("w"),
        )

    def client_config(self) -> zenoh.Config:
        return zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{self.port}"], multicast_scouting=False)

    def _write_targets(self) -> None:
        targets = [f"127.0.0.1:{port}" for _, port in self.processes.values()]
        temporary = self.targets.with_suffix(".tmp")
        temporary.write_text(json.dumps([{"targets": targets}]))
        temporary.replace(self.targets)  # Prometheus never reads half a file

    def start(self) -> str:
        self.started += 1
        name, metrics_port = f"box-{self.started}", free_port()
        env = dict(os.environ, FAULTY_SERVE_FRAME_COST_S=str(self.frame_cost_s))
        command = [sys.executable, "-m", "tools.faulty_serve", "serve", "--model", self.model]
        command += ["-m", "client", "-e", f"tcp/127.0.0.1:{self.port}", "--no-multicast-scouting"]
        command += ["--threads", "1", "--no-preview", "--settings", str(self.settings), "--instance", name]
        command += ["--state-dir", str(self.scratch / name), "--metrics-port", str(metrics_port)]
        with (self.scratch / f"{name}.log").open("a") as log:
            process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=log, text=True, env=env)
        self.processes[name] = (process, metrics_port)
        self._write_targets()
        return name

    def stop_one(self) -> str:
        """SIGTERM to the newest instance, as a Deployment scaled down removes a pod; it drains by itself."""
        name = next(reversed(self.processes))
        process, _ = self.processes.pop(name)
        process.send_signal(signal.SIGTERM)
        self._write_targets()
        return name

    def close(self) -> None:
        for process, _ in self.processes.values():
            process.terminate()
        for process, _ in self.processes.values():
            try:
                process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                process.kill()
        self.prometheus.terminate()
        self.prometheus.wait(timeout=20)
        self.router.close()

    def query(self, promql: str) -> float | None:
        url = f"http://127.0.0.1:{self.prometheus_port}/api/v1/query?" + urllib.parse.urlencode({"query": promql})
        try:
            with urllib.request.urlopen(url, timeout=5) as answer:
                result = json.loads(answer.read())["data"]["result"]
        except OSError:
            return None
        if not result:
            return None
        value = float(result[0]["value"][1])
        return None if math.isnan(value) else value


@dataclass
class Controller:
    """The HPA's rules, as deploy/kubernetes sets them (scaled to a short run)."""

    target: float
    minimum: int
    maximum: int
    down_window_s: float
    up: tuple[int, float] = (2, 20.0)  # at most this many instances more per this many seconds
    down: tuple[int, float] = (1, 10.0)  # at most this many fewer per this many seconds
    tolerance: float = 0.1
    recommendations: list[tuple[float, int]] = field(default_factory=list)
    changes: list[tuple[float, int]] = field(default_factory=list)  # (when, +n or -n)

    def desired(self, now: float, current: int, metric: float | None) -> int:
        if metric is None:  # no maps in the window: KEDA's ignoreNullValues reads 0
            metric = 0.0
        ratio = metric / self.target
        raw = current if abs(ratio - 1.0) <= self.tolerance else math.ceil(current * ratio)
        raw = max(self.minimum, min(self.maximum, raw))
        self.recommendations = [(t, r) for t, r in self.recommendations if now - t <= self.down_window_s]
        self.recommendations.append((now, raw))
        if raw > current:
            room = self.up[0] - sum(n for t, n in self.changes if n > 0 and now - t < self.up[1])
            desired = current + max(0, min(raw - current, room))
        else:
            stable = min(current, max(r for _, r in self.recommendations))
            room = self.down[0] + sum(n for t, n in self.changes if n < 0 and now - t < self.down[1])
            desired = current - max(0, min(current - stable, room))
        if desired != current:
            self.changes.append((now, desired - current))
        return desired


def longest_gap(robots: list[SimulatedRobots], began: float, ended: float) -> float:
    """The longest stretch of [began, ended] a robot streaming throughout went without maps."""
    worst = 0.0
    for fleet in robots:
        for name in fleet.names:
            arrivals = [a.at for a in fleet.received(name)]
            before = [at for at in arrivals if at < began]
            times = [before[-1] if before else began, *(at for at in arrivals if began <= at <= ended), ended]
            worst = max(worst, *(later - earlier for earlier, later in itertools.pairwise(times)))
    return worst


def quantile(values: list[float], q: float) -> float:
    if not values:
        return math.nan
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q * (len(ordered) - 1)))]


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", help="checkpoint (default: a tiny random one: the backend's cost is slept)")
    parser.add_argument("--frame-cost", type=float, default=0.2, help="test backend: seconds per inference [0.2]")
    parser.add_argument("--fps", type=float, default=2.0, help="each robot's frame rate [2]")
    parser.add_argument("--signal", choices=sorted(QUERIES), default="busy", help="what to scale on [busy]")
    parser.add_argument("--target", type=float, help="busy: inference s/s per instance [0.7]; age: p95 s [0.8]")
    parser.add_argument("--period", type=float, default=5.0, help="controller period, s [5]")
    parser.add_argument("--down-window", type=float, default=30.0, help="scale-down stabilisation, s [30]")
    parser.add_argument("--window", type=int, default=10, help="PromQL rate window, s [10]")
    parser.add_argument("--min", type=int, default=1, dest="minimum")
    parser.add_argument("--max", type=int, default=6, dest="maximum")
    parser.add_argument("--phases", default="2:60,8:120,2:120", help="robots:seconds,... [2:60,8:120,2:120]")
    parser.add_argument("--quick", action="store_true", help="short phases (2:20,6:40,2:40): correctness only")
    parser.add_argument("--out", type=Path, help="write the results as JSON here")
    return parser.parse_args()


def phase_result(
    robots: int,
    seconds: int,
    live: list[SimulatedRobots],
    window: tuple[float, float],
    events: list[Event],
    counts: list[int],
) -> dict[str, Any]:
    began, ended = window
    ages = [a.latency_ms / 1e3 for group in live for a in group.received(since=began, until=ended)]
    mine = [e for e in events if began <= e.at <= ended]
    kinds = [e.kind for e in mine]
    return {
        "robots": robots,
        "seconds": seconds,
        "instances": counts,  # at each controller period
        "map_age_p50_s": quantile(ages, 0.5),
        "map_age_p95_s": quantile(ages, 0.95),
        "maps": len(ages),
        "stale_maps": sum(age > MAX_FRAME_AGE_S for age in ages),
        "scale_events": [
            {
                "kind": e.kind,
                "instance": e.instance,
                "instances_after": e.instances_after,
                "longest_gap_s": round(longest_gap(live, e.at, min(e.at + 10.0, ended)), 2),
                "longest_gap_before_s": round(longest_gap(live, max(began, e.at - 10.0), e.at), 2),
            }
            for e in mine
        ],
        "reversals": sum(a != b for a, b in itertools.pairwise(kinds)),  # up then down, or down then up
        "settled": not [e for e in mine if e.at >= ended - SETTLED_S],  # no change in the phase's last 30 s
    }


def run(args: argparse.Namespace, scratch: Path) -> dict[str, Any]:
    from tools.random_clipseg import benchmark_model

    ramp = "2:20,6:40,2:40" if args.quick else args.phases
    phases = [(int(robots), int(seconds)) for robots, seconds in (p.split(":") for p in ramp.split(","))]
    fleet = Fleet(benchmark_model(args.model, True, scratch), scratch, args.frame_cost)
    target = args.target if args.target is not None else TARGETS[args.signal]
    controller = Controller(target, args.minimum, args.maximum, args.down_window)
    jpeg = encode_jpeg(bench_image(), 85)
    client = TraversabilityClient(config=fleet.client_config(), timeout=5.0)
    live: list[SimulatedRobots] = []
    stopped: list[SimulatedRobots] = []
    subscribers: list[Any] = []
    events: list[Event] = []
    samples: list[dict[str, Any]] = []
    results: list[dict[str, Any]] = []
    try:
        fleet.start()
        time.sleep(10.0)  # the first instance loads its model and joins
        for robots, seconds in phases:
            streaming = sum(len(group.names) for group in live)
            if robots > streaming:
                names = [f"robot{len(stopped) + streaming + k}/front" for k in range(robots - streaming)]
                group = SimulatedRobots(client, names, args.fps, jpeg)
                subscribers.append(client.subscribe_maps("**", group.on_maps))
                group.start()
                live.append(group)
            while sum(len(group.names) for group in live) > robots:
                live[-1].stop()
                stopped.append(live.pop())
            began, counts = time.monotonic(), []
            while time.monotonic() - began < seconds:
                time.sleep(args.period)
                now, current = time.monotonic(), len(fleet.processes)
                metric = fleet.query(QUERIES[args.signal].format(window=args.window))
                if metric is not None and args.signal == "busy":
                    metric /= current
                desired = controller.desired(now, current, metric)
                counts.append(current)
                samples.append(
                    {"t": round(now, 1), "robots": robots, "instances": current, "metric": metric, "desired": desired}
                )
                while len(fleet.processes) < desired:
                    events.append(Event(now, "up", fleet.start(), len(fleet.processes)))
                while len(fleet.processes) > desired:
                    events.append(Event(now, "down", fleet.stop_one(), len(fleet.processes)))
            results.append(phase_result(robots, seconds, live, (began, time.monotonic()), events, counts))
            print(json.dumps(results[-1]), flush=True)
    finally:
        for group in live:
            group.stop()
        for subscriber in subscribers:
            subscriber.undeclare()
        client.close()
        fleet.close()
    return {"phases": results, "samples": samples, "args": {k: str(v) for k, v in vars(args).items()}}


def cpu_name() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor()


def main() -> int:
    args = parse_args()
    with tempfile.TemporaryDirectory(prefix="gcdtrav-autoscale-") as scratch:
        report = run(args, Path(scratch))
    report["cpu"], report["cpus"] = cpu_name(), os.cpu_count()
    print(f"CPU: {report['cpu']} ({report['cpus']} CPUs)")
    print(
        "| robots | instances | map age p50 / p95 | longest gap 10 s after each scale event (10 s before) "
        "| stale maps | settled (reversals) |"
    )
    print("|---|---|---|---|---|---|")
    for p in report["phases"]:
        events = p["scale_events"]
        gaps = ", ".join(
            f"{e['kind']} to {e['instances_after']}: {e['longest_gap_s']:.2f} s ({e['longest_gap_before_s']:.2f})"
            for e in events
        )
        counts = p["instances"]
        print(
            f"| {p['robots']} | {counts[0]} → {counts[-1]} | {p['map_age_p50_s']:.2f} / {p['map_age_p95_s']:.2f} s "
            f"| {gaps or '—'} | {p['stale_maps']} | {'yes' if p['settled'] else 'no'} ({p['reversals']}) |"
        )
    if args.out:
        args.out.write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
