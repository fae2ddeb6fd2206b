"""The service-level rows of the benchmark: end to end through zenoh on loopback, and throughput with
simulated robots against a `gcdtrav serve` process. Repository tooling (``benchmarks/bench.py``), not part
of the shipped `gcdtrav bench`, which times the model on the user's machine."""

from __future__ import annotations

import statistics
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from gcdtrav.client import TraversabilityClient, zenoh_config
from gcdtrav.schemas.images import encode_jpeg
from gcdtrav.service.commands.bench import Bench, Row, RssSampler, bench_image, make_row

from tools.loopback import (
    INFER_EVERY_FRAME,
    free_port,
    loopback_service,
    robots_throughput,
    service_processes,
    wait_for_statuses,
)


def run_zenoh(bench: Bench, precision: str, frames: int) -> None:
    """Image put to maps received over loopback, minus inference: the service's own overhead."""
    bench.log(f"  end to end through zenoh: {frames} frames of 640x480 JPEG ...")
    result = zenoh_end_to_end(bench.model_dir, precision, frames)
    bench.add(
        make_row(
            f"zenoh loopback e2e ({precision})",
            "zenoh",
            result["latency_ms"],
            result["peak_rss_mb"],
            f"overhead median {result['overhead_median_ms']:.1f} ms",
            overhead_median_ms=result["overhead_median_ms"],
            overhead_p95_ms=result["overhead_p95_ms"],
            frames=len(result["latency_ms"]),
        )
    )


def run_robots(bench: Bench, precision: str, counts: list[int], fps: float, seconds: float) -> None:
    """Service throughput with several robots streaming at once (latest-only keeps one frame per robot).

    The service runs as its own ``gcdtrav serve`` process, as deployed: the robots and their client do
    not share its interpreter, and the memory column is the service's alone.
    """
    jpeg = encode_jpeg(bench_image(), 90)
    port = free_port()
    with tempfile.TemporaryDirectory() as state:
        serve = ["--model", str(bench.model_dir), "--precision", precision, "-l", f"tcp/127.0.0.1:{port}"]
        serve += ["--no-multicast-scouting", "--instance", "bench-robots", "--state-dir", state, "--no-preview"]
        settings = Path(state) / "service.yaml"
        settings.write_text(INFER_EVERY_FRAME)
        serve += ["--settings", str(settings)]
        with service_processes([serve]) as (process,):
            endpoint = [f"tcp/127.0.0.1:{port}"]
            client = TraversabilityClient(config=zenoh_config(mode="peer", connect=endpoint, multicast_scouting=False))
            try:
                wait_for_statuses(client, 1)
                for count in counts:
                    bench.log(f"  {count} simulated robots x {fps:g} fps for {seconds:g} s ...")
                    with RssSampler(process.pid, interval=0.05) as rss:
                        result = robots_throughput(client, jpeg, count, fps, seconds, warmup_s=min(2.0, seconds))
                    bench.add(robots_row(count, fps, precision, result, rss.peak))
            finally:
                client.close()


def robots_row(count: int, fps: float, precision: str, result: dict[str, Any], service_rss_mb: float) -> Row:
    latency = result.pop("latency_ms")
    note = (
        f"{result['maps_per_s']:.2f} maps/s in all; per robot {result['maps_per_robot_min']}"
        f"-{result['maps_per_robot_max']} in {result['seconds']:g} s; latency = stamp to maps; RSS = service's"
    )
    row = make_row(f"{count} robots x {fps:g} fps ({precision})", "robots", latency, service_rss_mb, note, **result)
    row.fps = round(result["maps_per_s"], 2)  # throughput, not 1 / latency
    return row


def zenoh_end_to_end(model_dir: Path, precision: str, frames: int) -> dict[str, Any]:
    with loopback_service(model_dir, precision) as client:
        arrived: dict[int, tuple[float, float]] = {}
        done = threading.Event()

        def on_maps(maps: Any) -> None:
            arrived[maps.header.seq] = (time.perf_counter(), maps.header.inference_ms)
            done.set()

        subscriber = client.subscribe_maps("bench", on_maps)
        time.sleep(0.5)
        jpeg = encode_jpeg(bench_image(), 90)
        latencies, overheads = [], []
        with RssSampler() as rss:
            for index in range(frames + 3):  # 3 warm-up frames
                done.clear()
                sent = time.perf_counter()
                client.publish_image("bench", jpeg)
                if not done.wait(30):
                    raise RuntimeError("no maps within 30 s")
                received, inference = arrived[index]
                if index >= 3:
                    latencies.append((received - sent) * 1e3)
                    overheads.append((received - sent) * 1e3 - inference)
        subscriber.undeclare()
    return {
        "latency_ms": latencies,
        "overhead_median_ms": statistics.median(overheads),
        "overhead_p95_ms": float(np.percentile(overheads, 95)),
        "peak_rss_mb": rss.peak,
    }
