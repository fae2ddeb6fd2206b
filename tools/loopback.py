"""Simulated robots and an in-process service on 127.0.0.1, for the benchmark and the soak test.

Everything here stays on loopback, with multicast scouting off, and stops when its context ends.
"""

from __future__ import annotations

import contextlib
import math
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import zenoh
from gcdtrav.client import Maps, TraversabilityClient, zenoh_config
from gcdtrav.schemas.anchors import AnchorSet, default_anchor_set
from gcdtrav.schemas.settings import ServiceSettings

if TYPE_CHECKING:
    from gcdtrav.service.backends.base import SegmentationBackend
    from gcdtrav.service.bus.node import TraversabilityService


# These tools stream one image again and again to measure inference: reuse (issue 34) would answer all but
# the first frame of each robot without inferring. benchmarks/fleet_mix.py measures reuse itself.
INFER_EVERY_FRAME = "reuse: {enabled: false}\n"


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def listening(port: int) -> bool:
    """Whether something accepts TCP on the loopback ``port`` (a service or a router that came up)."""
    with socket.socket() as probe:
        return probe.connect_ex(("127.0.0.1", port)) == 0


def waits_before_dropping(config: zenoh.Config) -> zenoh.Config:
    """``config``, waiting up to 1 s (5 s for a fragmented sample) for a free batch before dropping a sample put
    with congestion control DROP (the service's maps, a put's default) instead of zenoh's 1 ms (50 ms): on a
    loaded 2-core machine the sending thread is not run that soon, and a test's one maps message, or a
    client's one 400 kB put, was lost. For the sessions of tests and benchmarks on loopback, not the product's."""
    config.insert_json5("transport/link/tx/queue/congestion_control/drop/wait_before_drop", "1000000")
    config.insert_json5("transport/link/tx/queue/congestion_control/drop/max_wait_before_drop_fragments", "5000000")
    return config


def serve_command(*arguments: str) -> list[str]:
    """The command line of ``gcdtrav serve ARGUMENTS`` with this Python."""
    return [sys.executable, "-m", "gcdtrav.service.commands.cli", "serve", *arguments]


@contextmanager
def service_processes(arguments: Sequence[Sequence[str]]) -> Iterator[list[subprocess.Popen[str]]]:
    """``gcdtrav serve ARGS`` once per argument list, as child processes; stopped (SIGTERM, then kill) at exit."""
    # Logs go to files, not pipes: nobody reads a pipe during a long soak, and a full one blocks the service.
    with contextlib.ExitStack() as logs:
        files = [logs.enter_context(tempfile.TemporaryFile("w+")) for _ in arguments]
        processes = [
            subprocess.Popen(serve_command(*args), stdout=subprocess.DEVNULL, stderr=log_file, text=True)
            for args, log_file in zip(arguments, files, strict=True)
        ]
        try:
            yield processes
        except BaseException:
            for log_file in files:  # why a service did not come up or failed: the end of its log
                log_file.seek(0)
                print("".join(log_file.readlines()[-20:]), file=sys.stderr)
            raise
        finally:
            for process in processes:
                process.terminate()
            for process in processes:
                try:
                    process.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    process.kill()


def wait_for_statuses(client: TraversabilityClient, instances: int, timeout_s: float = 120.0) -> None:
    """Until ``instances`` services answer status queries (model loading takes a while)."""
    began = time.monotonic()
    while time.monotonic() - began < timeout_s:
        try:
            if len(client.statuses(timeout=2.0)) >= instances:
                return
        except Exception:  # not up yet: no reply, or a reply from a service still starting
            pass
        time.sleep(0.5)
    raise RuntimeError(f"{instances} service instance(s) did not come up within {timeout_s:.0f} s")


def anchor_set_at_start(settings: ServiceSettings) -> AnchorSet:
    """The anchor set `gcdtrav serve` starts with for ``settings``: its store opened once for the read, as serve
    opens it (``store_at_start``), then closed (``in_process_service`` builds its own service on it)."""
    from gcdtrav.service.commands.serve import starting_anchor_set, store_at_start

    store = store_at_start(settings)
    try:
        return starting_anchor_set(settings, store)
    finally:
        if store is not None:
            store.close()


@contextmanager
def in_process_service(
    backend: SegmentationBackend, settings: ServiceSettings, anchors: AnchorSet | None = None
) -> Iterator[tuple[TraversabilityService, int]]:
    """A started service in this process on its own session, listening on a free loopback port, waiting before
    it drops a sample (``waits_before_dropping``).

    Yields the service and the port; ``anchors`` defaults to the paper's set. Stopped and closed at exit.
    """
    from gcdtrav.service.bus.node import TraversabilityService
    from gcdtrav.service.pipeline import Pipeline

    port = free_port()
    config = zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    session = zenoh.open(waits_before_dropping(config))
    try:
        pipeline = Pipeline(backend, anchors if anchors is not None else default_anchor_set(), settings.engine)
        service = TraversabilityService(session, pipeline, settings)
        service.start()
        try:
            yield service, port
        finally:
            service.stop()
    finally:
        session.close()


@contextmanager
def loopback_service(model_dir: Path, precision: str, instance: str = "bench") -> Iterator[TraversabilityClient]:
    """A service (default anchors, no preview) in this process and a client connected to it."""
    from gcdtrav.service.backends.clipseg import ClipSegBackend

    backend = ClipSegBackend(str(model_dir), precision=precision)
    with tempfile.TemporaryDirectory() as state:
        settings = ServiceSettings.model_validate(
            {"state_dir": state, "instance": instance, "preview": False, "reuse": {"enabled": False}}
        )
        with in_process_service(backend, settings) as (_, port):
            config = zenoh_config(mode="peer", connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
            with TraversabilityClient(config=waits_before_dropping(config)) as client:
                yield client


@dataclass(frozen=True)
class Arrival:
    at: float  # time.monotonic() when the maps arrived
    source: str
    latency_ms: float  # from the robot's stamp to arrival
    instance: str  # the service instance that made the maps


class SimulatedRobots:
    """Robot threads publishing one JPEG at a fixed rate; counts frames sent and maps received per robot."""

    def __init__(self, client: TraversabilityClient, names: list[str], fps: float, jpeg: bytes) -> None:
        self.client, self.fps, self.jpeg, self.names = client, fps, jpeg, names
        self.sent: dict[str, int] = defaultdict(int)
        self.arrivals: list[Arrival] = []  # one per maps message of these robots, in arrival order
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._threads: list[threading.Thread] = []

    def on_maps(self, maps: Maps) -> None:
        header = maps.header
        if header.source in self.names:
            arrival = Arrival(time.monotonic(), header.source, (time.time() - header.stamp) * 1e3, header.instance)
            with self._lock:
                self.arrivals.append(arrival)

    def received(self, source: str | None = None, since: float = -math.inf, until: float = math.inf) -> list[Arrival]:
        """Maps received (of one robot, or all), optionally within [since, until) on time.monotonic()."""
        with self._lock:
            arrivals = list(self.arrivals)
        return [a for a in arrivals if (source is None or a.source == source) and since <= a.at < until]

    def _run(self, name: str) -> None:
        period = 1.0 / self.fps
        next_at = time.monotonic()
        while not self._stop.is_set():
            self.client.publish_image(name, self.jpeg, stamp=time.time())
            self.sent[name] += 1
            next_at += period
            self._stop.wait(max(0.0, next_at - time.monotonic()))

    def start(self) -> None:
        """Start streaming (again, after ``stop``)."""
        self._stop.clear()
        self._threads = [threading.Thread(target=self._run, args=(name,), daemon=True) for name in self.names]
        for thread in self._threads:
            thread.start()

    def stop(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(5)


def robots_throughput(
    client: TraversabilityClient, jpeg: bytes, robots: int, fps: float, seconds: float, warmup_s: float = 2.0
) -> dict[str, Any]:
    """N robots streaming at ``fps`` each for ``seconds`` (after a warm-up): maps/s and latency."""
    names = [f"robot{robots}-{k}/front" for k in range(robots)]
    fleet = SimulatedRobots(client, names, fps, jpeg)
    subscriber = client.subscribe_maps("**", fleet.on_maps)
    time.sleep(0.3)
    try:
        fleet.start()
        time.sleep(warmup_s)
        began = time.monotonic()
        time.sleep(seconds)
        ended = time.monotonic()
    finally:
        fleet.stop()
        time.sleep(0.5)
        subscriber.undeclare()
    window = fleet.received(since=began, until=ended)
    per_robot = [sum(1 for a in window if a.source == name) for name in names]
    latency = [a.latency_ms for a in window]
    return {
        "robots": robots,
        "fps_per_robot": fps,
        "seconds": round(ended - began, 2),
        "maps_per_s": len(window) / (ended - began),
        "maps_per_robot_min": min(per_robot),
        "maps_per_robot_max": max(per_robot),
        "latency_ms": latency or [float("nan")],
        "latency_median_ms": statistics.median(latency) if latency else float("nan"),
        "latency_p95_ms": float(np.percentile(latency, 95)) if latency else float("nan"),
    }


def sqlite_outbox(path: Path, max_pairs: int, max_bytes: int, bound: int = 100_000) -> Any:
    """An opened and started outbox over a SQLite file: a single process's store (tests, benchmarks)."""
    from gcdtrav.service.store.outbox import PairOutbox
    from gcdtrav.service.store.sqlite import SqliteStore

    outbox = PairOutbox(lambda: SqliteStore(path), "sqlite", str(path), bound, max_pairs, max_bytes)
    outbox.open_now()
    outbox.start()
    return outbox


def admit(tracker: Any, source: str) -> bool:
    """A frame of ``source`` noted by a SourceTracker, admitting it if new and there is room (as the intake
    does: note, else promote); False if there is none."""
    from gcdtrav.service.runtime.intake.sources import SourcesFull

    if tracker.note(source):
        return True
    try:
        tracker.promote(source)
    except SourcesFull:
        return False
    return True


def grid_update(grids: Any, source: str, record: Any, weights: Any, **fuse: Any) -> Any:
    """A frame fused into ``grids`` (GridOutputs) and encoded at once, as the worker and the outputs do it in
    two steps; None when not fused (not a grid's camera, or no intrinsics, mount or pose)."""
    fused = grids.fuse(source, record, weights, **fuse)
    return fused.encode() if fused is not None else None
