"""Robots over real links: a 1920x1200 camera at 15 fps reaching the service through a shaped TCP link.

    python -m benchmarks.link                               # 2, 5, 20 Mbit/s, 50 ms each way, 60 s + 10 s outage
    python -m benchmarks.link --quick                       # smoke: tiny random model, 5 Mbit/s, a few seconds
    python -m benchmarks.link --model ./clipseg-rd64-refined --mbit 2 --seconds 120

Three ways per link, each with the robot's zenoh session in client mode through tools/shaping_proxy.py
(token bucket + one-way delay, both directions) to the service's peer; shared memory off on both ends (it
would carry large payloads between processes of one host around the proxy) and 64 kB socket buffers (a
radio's queue, not a loopback's megabytes):

- ``raw``: the camera's sensor_msgs/Image (rgb8, 6.9 MB) as rmw_zenoh publishes it, subscribed by the
  service directly (``ros_inputs``); the robot's consumer subscribes to ``maps``;
- ``compressed``: its CompressedImage (JPEG, about 0.4 MB), directly, consumer on ``maps``;
- ``relay``: the Image on the robot's own bus, ``gcdtrav relay`` across the link (credits, frames at the
  model's size, JPEG), the consumer on the robot's bus on ``maps8`` (compact).

Reported per case: link bytes/s each way, maps/s at the robot, the age of the robot's newest map sampled
every 0.1 s (p50/p95/max: how old the map a planner holds is), frames computed already stale (published
more than ``--stale-s`` after capture), the service's stale drops, bytes per map of the form used, and an
outage of ``--outage-s``: the time from the link's return to the first fresh map (age at arrival at most
``--stale-s``). Everything runs on 127.0.0.1 and stops by itself; the JSON goes to ``--out``.

Do not time this on a busy machine: the service's inference and the camera's copies share its CPUs.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from gcdtrav.client import TraversabilityClient, zenoh_config
from gcdtrav.client.relay.relay import Relay
from gcdtrav.schemas.images import encode_jpeg
from gcdtrav.schemas.messages import peek_fields
from gcdtrav.schemas.relay import RelaySettings
from gcdtrav.service.commands.bench import bench_image

from tools.loopback import INFER_EVERY_FRAME, free_port, service_processes, wait_for_statuses
from tools.ros_fixtures import compressed_image_cdr, image_cdr
from tools.shaping_proxy import LinkShape, ShapingProxy

WAYS = ("raw", "compressed", "relay")
SOCKET_BUFFER = 64 * 1024
AGE_SAMPLE_S = 0.1
IMAGE_TYPE_CHUNK = "sensor_msgs::msg::dds_::Image_/RIHS01_bench"
COMPRESSED_TYPE_CHUNK = "sensor_msgs::msg::dds_::CompressedImage_/RIHS01_bench"


def link_config(port: int, mode: str = "client") -> zenoh.Config:
    """A session through the shaped link: no shared memory, no scouting, small socket buffers."""
    config = zenoh_config(mode=mode, connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    config.insert_json5("transport/shared_memory/enabled", "false")
    config.insert_json5("transport/link/tcp", json.dumps({"so_sndbuf": SOCKET_BUFFER, "so_rcvbuf": SOCKET_BUFFER}))
    return config


class Camera:
    """A 1920x1200 camera: a few synthetic frames in turn, stamped when published, at ``fps``."""

    def __init__(self, session: zenoh.Session, key: str, payload: Callable[[int, float], bytes], fps: float) -> None:
        self.publisher = session.declare_publisher(key)
        self.payload, self.fps, self.sent = payload, fps, 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        next_at = time.monotonic()
        while not self._stop.is_set():
            with contextlib.suppress(zenoh.ZError):  # the session reconnects after an outage
                self.publisher.put(self.payload(self.sent, time.time()))
            self.sent += 1
            next_at += 1 / self.fps
            self._stop.wait(max(0.0, next_at - time.monotonic()))

    def start(self) -> Camera:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(10)


@dataclass
class RobotMaps:
    """The maps the robot's consumer receives: arrivals, and the newest map's age sampled over time."""

    arrivals: list[tuple[float, float, float, int]] = field(default_factory=list)  # (now, stamp, published, bytes)
    ages: list[tuple[float, float]] = field(default_factory=list)  # (now, age of the newest map)
    _newest: float = -np.inf
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _stop: threading.Event = field(default_factory=threading.Event)

    def on_sample(self, sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        header = peek_fields(payload, ("header",))["header"]
        with self._lock:
            self.arrivals.append((time.time(), header["stamp"], header["published_at"], len(payload)))
            self._newest = max(self._newest, header["stamp"])

    def sample_ages(self) -> None:
        while not self._stop.wait(AGE_SAMPLE_S):
            now = time.time()
            with self._lock:
                self.ages.append((now, now - self._newest))

    def window(self, began: float, ended: float) -> tuple[list[tuple[float, float, float, int]], list[float]]:
        with self._lock:
            arrivals = [a for a in self.arrivals if began <= a[0] < ended]
            ages = [age for at, age in self.ages if began <= at < ended]
        return arrivals, ages


def percentiles(values: list[float]) -> dict[str, float | None]:
    finite = [v for v in values if np.isfinite(v)]
    if not finite:
        return {"p50": None, "p95": None, "max": None, "never": len(values) - len(finite)}
    p50, p95 = np.percentile(finite, [50, 95])
    return {"p50": round(float(p50), 3), "p95": round(float(p95), 3), "max": round(max(finite), 3)}


def camera_frames(way: str, count: int = 4) -> Callable[[int, float], bytes]:
    """The payload of frame k at a stamp: raw Image CDR (the header's stamp patched in place) or CompressedImage."""
    images = [bench_image(1200, 1920, seed=k) for k in range(count)]
    if way == "compressed":
        jpegs = [encode_jpeg(image, 80) for image in images]
        return lambda k, stamp: compressed_image_cdr(jpegs[k % count], stamp, "camera")
    raws = [bytearray(image_cdr(image, 0.0, "camera")) for image in images]

    def raw(k: int, stamp: float) -> bytes:
        payload = raws[k % count]
        sec = int(stamp)
        payload[4:12] = np.array([sec], "<i4").tobytes() + np.array([int((stamp - sec) * 1e9)], "<u4").tobytes()
        return bytes(payload)

    return raw


@contextmanager
def robot(way: str, proxy_port: int, source: str, args: argparse.Namespace, maps: RobotMaps) -> Iterator[Any]:
    """The robot of one way: its sessions, camera and consumer; yields the relay (or None)."""
    topic = f"0/{source}/image_raw"
    with ExitStack() as stack:
        if way in ("raw", "compressed"):
            session = zenoh.open(link_config(proxy_port))
            stack.callback(session.close)
            chunk = IMAGE_TYPE_CHUNK if way == "raw" else COMPRESSED_TYPE_CHUNK
            consumer = session.declare_subscriber(f"gcdtrav/out/{source}/image_raw/maps", maps.on_sample)
            stack.callback(consumer.undeclare)
            camera = Camera(session, f"{topic}/{chunk}", camera_frames(way), args.fps).start()
            stack.callback(camera.stop)
            yield None
            return
        bus_port = free_port()
        bus = zenoh.open(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{bus_port}"], multicast_scouting=False))
        stack.callback(bus.close)
        link = zenoh.open(link_config(proxy_port))
        stack.callback(link.close)
        local = zenoh.open(zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{bus_port}"], multicast_scouting=False))
        stack.callback(local.close)
        settings = RelaySettings.model_validate(
            {"cameras": [{"camera": f"/{source}/image_raw", "source": source}], "jpeg_quality": args.jpeg_quality}
        )
        relay = Relay(settings, link, local).start()
        stack.callback(relay.close)
        consumer = bus.declare_subscriber(f"gcdtrav/out/{source}/maps8", maps.on_sample)
        stack.callback(consumer.undeclare)
        camera = Camera(bus, f"{topic}/{IMAGE_TYPE_CHUNK}", camera_frames("raw"), args.fps).start()
        stack.callback(camera.stop)
        yield relay


def service_counts(client: TraversabilityClient, source: str) -> dict[str, Any]:
    for status in client.statuses(timeout=5.0):
        if source in status.sources:
            s = status.sources[source]
            return {"received": s.received, "processed": s.processed, "dropped": s.dropped, "stale": s.stale}
    return {}


def run_case(
    way: str, mbit: float, service_port: int, observer: TraversabilityClient, args: argparse.Namespace
) -> dict[str, Any]:
    source = f"bench/{way}_{mbit:g}".replace(".", "_")
    shape = LinkShape(mbit * 1e6, args.delay_ms / 1e3, socket_buffer_bytes=SOCKET_BUFFER)
    proxy = ShapingProxy(("127.0.0.1", service_port), shape).start()
    maps = RobotMaps()
    sampler = threading.Thread(target=maps.sample_ages, daemon=True)
    print(f"  {way} at {mbit:g} Mbit/s ...", file=sys.stderr)
    try:
        with robot(way, proxy.port, source, args, maps):
            sampler.start()
            time.sleep(args.warmup)
            began, (up0, down0) = time.time(), proxy.delivered()
            time.sleep(args.seconds)
            ended, (up1, down1) = time.time(), proxy.delivered()
            steady = service_counts(observer, f"{source}/image_raw" if way != "relay" else source)
            proxy.outage()
            time.sleep(args.outage_s)
            proxy.outage(down=False)
            restored = time.time()
            recovery = wait_for_fresh(maps, restored, args)
            after = service_counts(observer, f"{source}/image_raw" if way != "relay" else source)
    finally:
        maps._stop.set()
        proxy.stop()
    arrivals, ages = maps.window(began, ended)
    seconds = ended - began
    return {
        "way": way,
        "mbit": mbit,
        "delay_ms": args.delay_ms,
        "seconds": round(seconds, 1),
        "link_up_bytes_per_s": round((up1 - up0) / seconds),
        "link_down_bytes_per_s": round((down1 - down0) / seconds),
        "maps_per_s": round(len(arrivals) / seconds, 3),
        "map_age_s": percentiles(ages),
        "age_at_arrival_s": percentiles([now - stamp for now, stamp, _, _ in arrivals]),
        "computed_stale": sum(1 for _, stamp, published, _ in arrivals if published - stamp > args.stale_s),
        "maps_bytes_mean": round(float(np.mean([n for *_, n in arrivals]))) if arrivals else None,
        "service": steady,
        "outage": {
            "seconds": args.outage_s,
            "recovery_s": None if recovery is None else round(recovery - restored, 2),
            "computed_stale_after": sum(
                1 for now, stamp, published, _ in maps.arrivals if now >= restored and published - stamp > args.stale_s
            ),
            "service_after": after,
        },
    }


def wait_for_fresh(maps: RobotMaps, restored: float, args: argparse.Namespace) -> float | None:
    """When the first map captured at most ``stale_s`` before its arrival came after the link returned."""
    deadline = time.monotonic() + args.recovery_timeout
    while time.monotonic() < deadline:
        with maps._lock:
            fresh = [now for now, stamp, _, _ in maps.arrivals if now >= restored and now - stamp <= args.stale_s]
        if fresh:
            return fresh[0]
        time.sleep(0.1)
    return None


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default=None, help="checkpoint directory [random weights, real architecture]")
    parser.add_argument("--precision", default="fp32", help="the service's precision [fp32: no start-up timing]")
    parser.add_argument("--threads", type=int, default=None, help="torch threads of the service")
    parser.add_argument("--mbit", type=float, action="append", help="link rates, Mbit/s [2, 5, 20]")
    parser.add_argument("--ways", default=",".join(WAYS), help=f"comma list of {', '.join(WAYS)}")
    parser.add_argument("--delay-ms", type=float, default=50.0, help="one-way delay [50]")
    parser.add_argument("--fps", type=float, default=15.0, help="camera frames per second [15]")
    parser.add_argument("--seconds", type=float, default=60.0, help="steady window per case [60]")
    parser.add_argument("--warmup", type=float, default=10.0, help="seconds before the window [10]")
    parser.add_argument("--outage-s", type=float, default=10.0, help="link outage after the window [10]")
    parser.add_argument("--recovery-timeout", type=float, default=60.0, help="wait for a fresh map at most [60]")
    parser.add_argument("--stale-s", type=float, default=2.0, help="a map older than this is stale [2]")
    parser.add_argument("--max-frame-age-s", type=float, default=5.0, help="the service's max_frame_age_s [5]")
    parser.add_argument("--jpeg-quality", type=int, default=80, help="the relay's JPEG quality [80]")
    parser.add_argument("--quick", action="store_true", help="smoke: tiny random model, 5 Mbit/s, short windows")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/link.json"))
    args = parser.parse_args()
    if args.quick:
        args.mbit = args.mbit or [5.0]
        args.seconds, args.warmup, args.outage_s, args.recovery_timeout = 4.0, 4.0, 3.0, 30.0
    args.mbit = args.mbit or [2.0, 5.0, 20.0]
    args.ways = [way for way in args.ways.split(",") if way]
    if unknown := set(args.ways) - set(WAYS):
        parser.error(f"unknown ways {sorted(unknown)}; choose from {', '.join(WAYS)}")
    return args


def model_for(args: argparse.Namespace, scratch: Path) -> str:
    from tools.random_clipseg import benchmark_model

    return benchmark_model(args.model, args.quick, scratch)


def main() -> int:
    args = parse_args()
    with tempfile.TemporaryDirectory(prefix="gcdtrav-link-") as scratch_name, ExitStack() as stack:
        scratch = Path(scratch_name)
        port = free_port()
        settings = scratch / "service.yaml"
        settings.write_text(
            f"max_frame_age_s: {args.max_frame_age_s}\npreview: false\n"
            "ros_inputs:\n  - {key: '0/**', layout: rmw_zenoh}\n" + INFER_EVERY_FRAME
        )
        command = ["--model", model_for(args, scratch), "--precision", args.precision, "--instance", "link-bench"]
        command += ["-l", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting", "--settings", str(settings)]
        command += ["--state-dir", str(scratch / "state"), "--cfg", "transport/shared_memory/enabled:false"]
        buffers = json.dumps({"so_sndbuf": SOCKET_BUFFER, "so_rcvbuf": SOCKET_BUFFER})
        command += ["--cfg", f"transport/link/tcp:{buffers}"]
        if args.threads:
            command += ["--threads", str(args.threads)]
        stack.enter_context(service_processes([command]))
        observer = stack.enter_context(
            # a peer retries connecting while the service starts (a client gives up at once)
            TraversabilityClient(
                config=zenoh_config(mode="peer", connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
            )
        )
        wait_for_statuses(observer, 1, timeout_s=600)
        print(f"link benchmark: {args.ways} at {args.mbit} Mbit/s, {args.delay_ms:g} ms one way", file=sys.stderr)
        cases = [run_case(way, mbit, port, observer, args) for mbit in args.mbit for way in args.ways]
    report = {"settings": vars(args) | {"out": str(args.out)}, "cases": cases}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print_table(cases)
    print(f"written: {args.out}")
    return 0


def print_table(cases: list[dict[str, Any]]) -> None:
    columns = "way, Mbit/s, up B/s, down B/s, maps/s, age p50, age p95, age max, stale computed, bytes/map, recovery s"
    print("| " + " | ".join(columns.split(", ")) + " |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for c in cases:
        age = c["map_age_s"]
        print(
            f"| {c['way']} | {c['mbit']:g} | {c['link_up_bytes_per_s']} | {c['link_down_bytes_per_s']} | "
            f"{c['maps_per_s']} | {age['p50']} | {age['p95']} | {age['max']} | {c['computed_stale']} | "
            f"{c['maps_bytes_mean']} | {c['outage']['recovery_s']} |"
        )


if __name__ == "__main__":
    sys.exit(main())
