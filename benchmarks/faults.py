"""Fault benchmark (issue 26): robots keep being served while instances, the router or the disk fail, on loopback.

    python -m benchmarks.faults                      # all 7 faults, a few minutes
    python -m benchmarks.faults --quick              # SIGKILL, hang, flood with short windows, < 90 s
    python -m benchmarks.faults --faults sigkill,flood --out results/faults.json

A zenoh router on 127.0.0.1, 2 `gcdtrav serve` instances in client mode with deploy/service-zenoh.json5's
lease and retry timings (via --cfg), started through tools/faulty_serve.py (the real serve, plus a hang flag
and a full state dir), 6 robots publishing at --fps with stamps = now, and a consumer recording every map
(source, instance, stamp, order, arrival). Each fault runs on a fresh pair of instances and reports: blind time
per robot (longest gap between its maps beyond its frame time), maps older than max_frame_age_s on arrival,
maps out of order per robot (older order after newer, the client's own reordering off), frames lost by reason
(the instances' rejected/dropped_by_reason at the end) and each live instance's anchor-set version.
Without --model it uses tiny random weights (tools/random_clipseg.py, as the tests do): the faults, not the
model, are measured.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh
from gcdtrav.client import Maps, ServiceError, TraversabilityClient, zenoh_config
from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.schemas.images import encode_jpeg
from gcdtrav.service.commands.bench import bench_image

from tools.loopback import INFER_EVERY_FRAME, SimulatedRobots, free_port, wait_for_statuses

MAX_FRAME_AGE_S = 5.0  # the services' default, checked at the consumer
BLIND_GOAL_S = 3.0  # beyond the frame time, for faults of a single instance
SWAP_GOAL_S = 2.0
STEADY_GOAL = 0.9  # issue 32: the steady robots keep this share of their maps/s during a one-process flood
TINY_INPUT_SIZE = 96  # tests/conftest.py's tiny model
SINGLE_INSTANCE_FAULTS = {"sigkill", "sigstop", "hang", "full_disk"}
ALL_FAULTS = ["sigkill", "sigstop", "hang", "router_restart", "full_disk", "flood", "swap_during_hang"]
QUICK_FAULTS = ["sigkill", "hang", "flood"]
# deploy/service-zenoh.json5's timings: lease 2 s with 4 keep-alives, reconnect retry from 250 ms to 1 s.
DEPLOY_CFG = [
    "transport/link/tx/lease:2000",
    "transport/link/tx/keep_alive:4",
    "connect/retry:{period_init_ms:250,period_max_ms:1000,period_increase_factor:1.5}",
]


@dataclass(frozen=True)
class MapArrival:
    at: float  # time.monotonic()
    wall: float  # time.time(), against the robot's stamp
    source: str
    instance: str
    stamp: float
    order: tuple[float, float]


@dataclass
class Consumer:
    """Every map of every source, in arrival order (the client's own in-order filter off)."""

    arrivals: list[MapArrival] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_maps(self, maps: Maps) -> None:
        header = maps.header
        order = (header.order[0], header.order[1]) if header.order else (header.stamp, header.received_at)
        arrival = MapArrival(time.monotonic(), time.time(), header.source, header.instance, header.stamp, order)
        with self.lock:
            self.arrivals.append(arrival)

    def of(self, source: str, since: float = 0.0) -> list[MapArrival]:
        with self.lock:
            return [a for a in self.arrivals if a.source == source and a.at >= since]


class Fleet:
    """The router (in this process, so that it can restart on its port) and the service instances."""

    def __init__(self, model: str, scratch: Path, threads: int) -> None:
        self.port, self.scratch = free_port(), scratch
        self.router: zenoh.Session | None = None
        self.start_router()
        settings = scratch / "faults.yaml"
        settings.write_text(f"max_frame_age_s: {MAX_FRAME_AGE_S}\n{INFER_EVERY_FRAME}")
        self.common = ["--model", model, "-m", "client", "-e", f"tcp/127.0.0.1:{self.port}"]
        self.common += [
            "--no-multicast-scouting",
            "--threads",
            str(threads),
            "--no-preview",
            "--settings",
            str(settings),
        ]
        for item in DEPLOY_CFG:
            self.common += ["--cfg", item]
        self.processes: dict[str, subprocess.Popen[str]] = {}
        self.logs: dict[str, Path] = {}

    def start_router(self) -> None:
        config = zenoh_config(mode="router", listen=[f"tcp/127.0.0.1:{self.port}"], multicast_scouting=False)
        self.router = zenoh.open(config)

    def stop_router(self) -> None:
        if self.router is not None:
            self.router.close()
            self.router = None

    def client_config(self) -> zenoh.Config:
        config = zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{self.port}"], multicast_scouting=False)
        config.insert_json5("connect/retry", "{period_init_ms:250,period_max_ms:1000,period_increase_factor:1.5}")
        return config

    def hang_flag(self, instance: str) -> Path:
        return self.scratch / f"hang-{instance}"

    def state_dir(self, instance: str) -> Path:
        return self.scratch / f"state-{instance}"

    def start(self, instance: str, full_disk: bool = False) -> None:
        env = dict(os.environ, FAULTY_SERVE_HANG_FLAG=str(self.hang_flag(instance)))
        if full_disk:
            env["FAULTY_SERVE_FULL_DIR"] = str(self.state_dir(instance))
        command = [sys.executable, "-m", "tools.faulty_serve", "serve", *self.common, "--instance", instance]
        command += ["--state-dir", str(self.state_dir(instance))]
        self.logs[instance] = self.scratch / f"{instance}.log"
        with self.logs[instance].open("a") as log:  # a file, never a pipe nobody reads
            self.processes[instance] = subprocess.Popen(
                command, stdout=subprocess.DEVNULL, stderr=log, text=True, env=env
            )

    def signal(self, instance: str, signum: int) -> None:
        self.processes[instance].send_signal(signum)

    def stop(self, instance: str) -> None:
        process = self.processes.pop(instance)
        if process.poll() is None:
            process.send_signal(signal.SIGCONT)
            process.terminate()
            try:
                process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()

    def close(self) -> None:
        for instance in list(self.processes):
            self.stop(instance)
        self.stop_router()

    def log_tail(self, instance: str) -> str:
        return "".join(self.logs[instance].read_text().splitlines(keepends=True)[-15:])


def blind_s(arrivals: list[MapArrival], began: float, ended: float, frame_s: float) -> float:
    """Longest stretch of [began, ended] without a map of this robot, beyond its frame time."""
    times = [began, *(a.at for a in arrivals if began <= a.at <= ended), ended]
    return max(0.0, max(b - a for a, b in itertools.pairwise(times)) - frame_s)


def out_of_order(arrivals: list[MapArrival]) -> int:
    newest: tuple[float, float] | None = None
    count = 0
    for arrival in arrivals:
        if newest is not None and arrival.order < newest:
            count += 1
        else:
            newest = arrival.order
    return count


def statuses_by_instance(client: TraversabilityClient) -> dict[str, Any]:
    try:
        return {s.instance: s for s in client.statuses(timeout=3.0)}
    except ServiceError:
        return {}


def final_statuses(client: TraversabilityClient, live: set[str], timeout_s: float = 15.0) -> dict[str, Any]:
    """Every live instance's status (a busy instance may miss a query or two)."""
    statuses: dict[str, Any] = {}
    began = time.monotonic()
    while time.monotonic() - began < timeout_s and not live <= set(statuses):
        statuses |= statuses_by_instance(client)
    return statuses


def anchor_versions(client: TraversabilityClient) -> dict[str, str]:
    return {name: s.anchor_set_version for name, s in statuses_by_instance(client).items()}


def wait_versions_agree(client: TraversabilityClient, live: set[str], timeout_s: float) -> float | None:
    """Seconds until every live instance reports the same anchor version, or None."""
    began = time.monotonic()
    while time.monotonic() - began < timeout_s:
        versions = anchor_versions(client)
        if live <= set(versions) and len({versions[name] for name in live}) == 1:
            return round(time.monotonic() - began, 2)
        time.sleep(0.1)
    return None


def swapped_set(tag: str) -> str:
    anchors = json.loads(default_anchor_set().to_json())
    anchors["anchors"][0]["concept"] = f"{anchors['anchors'][0]['concept']} {tag}"
    return json.dumps(anchors)


def try_swap(client: TraversabilityClient, tag: str) -> dict[str, Any]:
    """What the client says to a swap: the version, or the error's kind and message."""
    began = time.monotonic()
    try:
        version = client.set_anchors(swapped_set(tag), timeout=5.0)
        outcome: dict[str, Any] = {"result": "swapped", "version": version}
    except ServiceError as err:
        outcome = {"result": type(err).__name__, "message": str(err)[:300]}
        outcome |= {"swapped": getattr(err, "swapped", None)}
    return outcome | {"took_s": round(time.monotonic() - began, 2)}


FLOOD_CODE = """
import sys, time, zenoh
from gcdtrav.client import zenoh_config
port, prefix, seconds, rate, identified = sys.argv[1], sys.argv[2], float(sys.argv[3]), float(sys.argv[4]), sys.argv[5]
config = zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
session = zenoh.open(config)
me = session.declare_publisher(f"{prefix}/flood/me").id if identified == "yes" else None
sent, began = 0, time.monotonic()
end = began + seconds
while time.monotonic() < end:
    info = zenoh.SourceInfo(me, sent + 1) if me is not None else None
    session.put(f"{prefix}/flood/n{sent:07d}", b"not an image", source_info=info)
    sent += 1
    if rate > 0:
        time.sleep(max(0.0, began + sent / rate - time.monotonic()))
print(sent, began, time.monotonic())
session.close()
"""


def flood(port: int, prefix: str, seconds: float, rate: float, identified: bool) -> subprocess.Popen[str]:
    """A process putting undecodable frames, each under a new source name, ``rate`` a second (0: as fast as it
    can) for ``seconds``, saying who it is in zenoh's source info (as our client does) if ``identified``
    (a process of its own: in this one it would starve the robots' threads of the interpreter lock). It prints
    how many it sent and when it began and ended (time.monotonic, the same clock in every process)."""
    command = [sys.executable, "-c", FLOOD_CODE, str(port), prefix, str(seconds), str(rate)]
    command.append("yes" if identified else "no")
    return subprocess.Popen(command, stdout=subprocess.PIPE, text=True)


@dataclass
class Window:
    """Timings of one fault run."""

    fps: float
    warmup_s: float
    fault_s: float  # how long the fault lasts (SIGSTOP, hang, flood, router down)
    after_s: float  # watched after the fault ends
    flood_rate: float = 0.0  # new names a second; 0: as fast as one process can
    flood_identified: bool = True  # the flooder sets source info (its own intake bucket); False: anonymous


FaultAction = Callable[["Run"], dict[str, Any]]


@dataclass
class Run:
    fleet: Fleet
    client: TraversabilityClient
    window: Window
    consumer: Consumer
    robots: SimulatedRobots
    victim: str = "faults-0"


def fault_sigkill(run: Run) -> dict[str, Any]:
    run.fleet.signal(run.victim, signal.SIGKILL)
    time.sleep(run.window.fault_s + run.window.after_s)
    return {"live": ["faults-1"]}


def fault_sigstop(run: Run) -> dict[str, Any]:
    run.fleet.signal(run.victim, signal.SIGSTOP)
    time.sleep(run.window.fault_s)
    run.fleet.signal(run.victim, signal.SIGCONT)
    time.sleep(run.window.after_s)
    return {"live": ["faults-0", "faults-1"]}


def fault_hang(run: Run) -> dict[str, Any]:
    flag = run.fleet.hang_flag(run.victim)
    flag.touch()
    time.sleep(run.window.fault_s)
    flag.unlink()
    time.sleep(run.window.after_s)
    return {"live": ["faults-0", "faults-1"]}


def fault_router_restart(run: Run) -> dict[str, Any]:
    run.fleet.stop_router()
    time.sleep(run.window.fault_s)
    run.fleet.start_router()
    time.sleep(run.window.after_s)
    return {"live": ["faults-0", "faults-1"]}


def fault_full_disk(run: Run) -> dict[str, Any]:
    """faults-0's state dir refuses writes (ENOSPC); a swap, then a restart of faults-0."""
    before = anchor_versions(run.client)
    swap = try_swap(run.client, "full-disk")
    after_swap = anchor_versions(run.client)
    time.sleep(run.window.fault_s)
    run.fleet.stop(run.victim)
    run.fleet.start(run.victim, full_disk=True)
    wait_for_statuses(run.client, 2, timeout_s=120)
    time.sleep(run.window.after_s)
    after_restart = anchor_versions(run.client)
    return {
        "live": ["faults-0", "faults-1"],
        "swap": swap,
        "versions_before": before,
        "versions_after_swap": after_swap,
        "versions_after_restart": after_restart,
        "restart_serves_old_set": after_restart.get(run.victim) == before.get(run.victim),
    }


def fault_flood(run: Run) -> dict[str, Any]:
    """A flood of new names for fault_s; a new robot starts 1 s into it (at 1/fps, like the others)."""
    newcomer, lead_s = "newcomer/front", min(1.0, run.window.fault_s / 2)
    window = run.window
    flooder = flood(run.fleet.port, run.client.input_prefix, window.fault_s, window.flood_rate, window.flood_identified)
    time.sleep(lead_s)
    first_sent, period, sent = time.monotonic(), 1.0 / window.fps, 0
    while time.monotonic() < first_sent + window.fault_s - lead_s:
        run.client.publish_image(newcomer, run.robots.jpeg, stamp=time.time())
        sent += 1
        time.sleep(max(0.0, first_sent + sent * period - time.monotonic()))
    flooded, _ = flooder.communicate(timeout=30)
    time.sleep(window.after_s)
    first = run.consumer.of(newcomer)
    count, began, ended = [*flooded.split(), "0", "0", "0"][:3]  # 0s: the flooder failed (its stderr says why)
    return {
        "live": ["faults-0", "faults-1"],
        "flood_frames": int(count),
        "flood_identified": window.flood_identified,
        "flood_window": (float(began), float(ended)),
        "newcomer_frames": sent,
        "newcomer_maps": len(first),
        "newcomer_first_map_s": round(first[0].at - first_sent, 3) if first else None,
    }


def maps_per_s(consumer: Consumer, names: list[str], began: float, ended: float) -> float:
    """Maps of the robots ``names`` that arrived within [began, ended), per second."""
    count = sum(1 for name in names for a in consumer.of(name) if began <= a.at < ended)
    return round(count / max(ended - began, 1e-9), 2)


def steady_rates(consumer: Consumer, names: list[str], warmed: float, fault: tuple[float, float]) -> dict[str, Any]:
    """The steady robots' maps/s before the flood (from ``warmed``) and while it lasts, and their ratio."""
    before = maps_per_s(consumer, names, warmed, fault[0])
    during = maps_per_s(consumer, names, fault[0], fault[1])
    ratio = round(during / before, 3) if before else None
    return {"steady_maps_per_s_before": before, "steady_maps_per_s_during": during, "steady_kept": ratio}


def fault_swap_during_hang(run: Run) -> dict[str, Any]:
    flag = run.fleet.hang_flag(run.victim)
    flag.touch()
    time.sleep(min(1.0, run.window.fault_s / 2))
    swap = try_swap(run.client, "during-hang")
    during = anchor_versions(run.client)
    time.sleep(max(0.0, run.window.fault_s - min(1.0, run.window.fault_s / 2) - swap["took_s"]))
    flag.unlink()
    agreed = wait_versions_agree(run.client, {"faults-0", "faults-1"}, timeout_s=10.0)
    time.sleep(run.window.after_s)
    return {
        "live": ["faults-0", "faults-1"],
        "swap": swap,
        "versions_during_hang": during,
        "versions_agree_after_hang_s": agreed,
    }


FAULTS: dict[str, FaultAction] = {
    "sigkill": fault_sigkill,
    "sigstop": fault_sigstop,
    "hang": fault_hang,
    "router_restart": fault_router_restart,
    "full_disk": fault_full_disk,
    "flood": fault_flood,
    "swap_during_hang": fault_swap_during_hang,
}


@contextlib.contextmanager
def fresh_pair(model: str, scratch: Path, threads: int, full_disk: bool) -> Iterator[Fleet]:
    fleet = Fleet(model, scratch, threads)
    try:
        fleet.start("faults-0", full_disk=full_disk)
        fleet.start("faults-1")
        yield fleet
    except BaseException:
        for name in fleet.logs:
            print(f"--- {name}\n{fleet.log_tail(name)}", file=sys.stderr)
        raise
    finally:
        fleet.close()


def measure(fault: str, model: str, window: Window, robots: int, threads: int) -> dict[str, Any]:
    with (
        tempfile.TemporaryDirectory() as scratch,
        fresh_pair(model, Path(scratch), threads, fault == "full_disk") as fleet,
    ):
        client = TraversabilityClient(config=fleet.client_config(), timeout=5.0)
        try:
            wait_for_statuses(client, 2, timeout_s=120)
            consumer = Consumer()
            subscriber = client.subscribe_maps("**", consumer.on_maps, in_order=False)
            names = [f"robot{k}/front" for k in range(robots)]
            fleet_robots = SimulatedRobots(client, names, window.fps, encode_jpeg(bench_image(240, 320), 85))
            time.sleep(0.5)
            fleet_robots.start()
            time.sleep(window.warmup_s)
            began = time.monotonic()
            warmed = began - max(window.warmup_s - 1.0, window.warmup_s / 2)  # the first maps take a moment
            run = Run(fleet, client, window, consumer, fleet_robots)
            details = FAULTS[fault](run)
            ended = time.monotonic()
            fleet_robots.stop()
            time.sleep(1.0)
            statuses = final_statuses(client, set(details["live"]))
            subscriber.undeclare()
        finally:
            client.close()
    frame_s = 1.0 / window.fps
    blind = {name: round(blind_s(consumer.of(name), began, ended, frame_s), 2) for name in names}
    every = [a for name in names for a in consumer.of(name)]
    return {
        "fault": fault,
        "window_s": round(ended - began, 1),
        "blind_s": blind,
        "blind_max_s": max(blind.values()),
        "stale_maps": sum(1 for a in every if a.wall - a.stamp > MAX_FRAME_AGE_S),
        "maps": len(every),
        "maps_by_instance_before": dict(Counter(a.instance for a in every if a.at < began)),
        "maps_by_instance_during": dict(Counter(a.instance for a in every if a.at >= began)),
        "out_of_order": {name: out_of_order(consumer.of(name)) for name in names},
        "rejected_by_reason": {name: dict(s.rejected_by_reason) for name, s in statuses.items()},
        "dropped_by_reason": {name: dict(s.dropped_by_reason) for name, s in statuses.items()},
        "anchor_versions": {name: s.anchor_set_version for name, s in statuses.items()},
        **details,
        **(steady_rates(consumer, names, warmed, details["flood_window"]) if "flood_window" in details else {}),
    }


def goals(result: dict[str, Any], fps: float) -> dict[str, bool]:
    """The issue's goals that apply to this fault."""
    checks = {"no_stale_map": result["stale_maps"] == 0}
    if result["fault"] in SINGLE_INSTANCE_FAULTS:
        checks["blind_within_3s"] = result["blind_max_s"] <= BLIND_GOAL_S
    live = [v for name, v in result["anchor_versions"].items() if name in result["live"]]
    checks["same_anchor_version"] = len(set(live)) == 1 and len(live) == len(result["live"])
    if result["fault"] == "swap_during_hang":
        agreed = result["versions_agree_after_hang_s"]
        checks["versions_agree_within_2s"] = agreed is not None and agreed <= SWAP_GOAL_S
    if result["fault"] == "full_disk":
        checks["restart_serves_old_set"] = result["restart_serves_old_set"]
    if result["fault"] == "flood":
        first = result["newcomer_first_map_s"]
        checks["newcomer_within_frame_time"] = first is not None and first <= 1.0 / fps
        kept = result["steady_kept"]
        checks["steady_keep_90pct"] = kept is not None and kept >= STEADY_GOAL
    return checks


def lost(result: dict[str, Any]) -> str:
    reasons: dict[str, int] = defaultdict(int)
    for table in ("rejected_by_reason", "dropped_by_reason"):
        for counts in result[table].values():
            for reason, count in counts.items():
                reasons[reason] += count
    return ", ".join(f"{r} {c}" for r, c in sorted(reasons.items())) or "-"


def table(results: list[dict[str, Any]]) -> str:
    rows = [
        "| fault | blind max s (beyond frame) | stale maps | out of order | lost by reason | anchor versions | "
        "extra | goals |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        extra: dict[str, Any] = {
            k: r[k]
            for k in (
                "newcomer_first_map_s",
                "flood_frames",
                "flood_identified",
                "steady_maps_per_s_before",
                "steady_maps_per_s_during",
                "steady_kept",
                "versions_agree_after_hang_s",
            )
            if k in r
        }
        if "swap" in r:
            extra["swap"] = r["swap"]["result"]
        if "restart_serves_old_set" in r:
            extra["restart_serves_old_set"] = r["restart_serves_old_set"]
        versions = ", ".join(f"{n}: {v[:8]}" for n, v in sorted(r["anchor_versions"].items()))
        verdict = ", ".join(f"{k} {'ok' if v else 'FAIL'}" for k, v in r["goals"].items())
        disorder = sum(r["out_of_order"].values())
        rows.append(
            f"| {r['fault']} | {r['blind_max_s']} | {r['stale_maps']} / {r['maps']} | {disorder} "
            f"| {lost(r)} | {versions} | {json.dumps(extra)} | {verdict} |"
        )
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help=f"{', '.join(QUICK_FAULTS)} with short windows")
    parser.add_argument("--faults", default=None, help=f"comma-separated, of {', '.join(ALL_FAULTS)} [all]")
    parser.add_argument("--robots", type=int, default=6)
    parser.add_argument("--fps", type=float, default=4.0)
    parser.add_argument("--model", default=None, help="checkpoint directory [tiny random weights]")
    parser.add_argument("--flood-rate", type=float, default=None, help="new names/s; 0: unbounded [0, quick 1000]")
    parser.add_argument(
        "--flood-anonymous", action="store_true", help="the flooder sets no source info (the shared intake bucket)"
    )
    parser.add_argument("--warmup-s", type=float, default=None, help="robots streaming before the fault [3, quick 2]")
    parser.add_argument("--threads", type=int, default=1, help="torch threads per instance [1]")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/faults.json"))
    args = parser.parse_args(argv)
    faults = args.faults.split(",") if args.faults else (QUICK_FAULTS if args.quick else ALL_FAULTS)
    if unknown := set(faults) - set(FAULTS):
        parser.error(f"unknown faults: {', '.join(sorted(unknown))}")
    window = Window(args.fps, 2.0, 5.0, 2.0, 1000.0) if args.quick else Window(args.fps, 3.0, 10.0, 5.0)
    if args.flood_rate is not None:
        window.flood_rate = args.flood_rate
    window.flood_identified = not args.flood_anonymous
    if args.warmup_s is not None:
        window.warmup_s = args.warmup_s

    from tools.random_clipseg import save_random_clipseg

    with tempfile.TemporaryDirectory() as models:
        model = args.model or str(save_random_clipseg(Path(models), preset="tiny", input_size=TINY_INPUT_SIZE))
        results = []
        for fault in faults:
            print(f"faults: {fault} ...", file=sys.stderr)
            result = measure(fault, model, window, args.robots, args.threads)
            result["goals"] = goals(result, args.fps)
            results.append(result)
    report: dict[str, Any] = {"settings": vars(args) | {"out": str(args.out), "faults": faults}}
    report |= {"window": vars(window), "results": results}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(table(results))
    print(f"written: {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
