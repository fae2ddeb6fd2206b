"""What `gcdtrav relay` itself costs on the robot: CPU and resident memory of the relay process while a
1920 x 1200 camera publishes raw rgb8 frames (6.9 MB each) at 15 fps on the robot's bus and a service on
loopback grants credits (tiny random model: credits come as fast as frames, the relay's upper bound).

    python -m benchmarks.relay_cost [--seconds 20] [--fps 15]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh
from gcdtrav.schemas.messages import ImageEnvelope
from gcdtrav.service.backends.cpus import cpu_name

from tools.loopback import free_port, listening
from tools.random_clipseg import save_random_clipseg

TICKS = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS  # utime + stime


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def wait_for_port(port: int, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if listening(port):
            return
        time.sleep(0.2)
    raise SystemExit(f"nothing listens on port {port}")


def camera(port: int, fps: float, stop: threading.Event) -> None:
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{port}"]')
    config.insert_json5("scouting/multicast/enabled", "false")
    frame = np.random.default_rng(0).integers(0, 256, (1200, 1920, 3), dtype=np.uint8).tobytes()
    with zenoh.open(config) as session:
        publisher = session.declare_publisher("robot/camera")
        next_at = time.monotonic()
        while not stop.is_set():
            envelope = ImageEnvelope(stamp=time.time(), encoding="rgb8", width=1920, height=1200, data=frame)
            publisher.put(envelope.pack())
            next_at += 1 / fps
            time.sleep(max(0.0, next_at - time.monotonic()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--fps", type=float, default=15.0)
    args = parser.parse_args()
    gcdtrav = [sys.executable, "-m", "gcdtrav.service.commands.cli"]
    with tempfile.TemporaryDirectory() as scratch:
        model = save_random_clipseg(Path(scratch) / "tiny", preset="tiny", input_size=96)
        link_port, robot_port = free_port(), free_port()
        stop = threading.Event()
        threading.Thread(target=camera, args=(robot_port, args.fps, stop), daemon=True).start()
        quiet = {"stdout": subprocess.DEVNULL, "stderr": open(Path(scratch) / "log", "w")}  # noqa: SIM115
        env = {**os.environ, "XDG_STATE_HOME": scratch, "XDG_CACHE_HOME": scratch}
        service = subprocess.Popen(
            [*gcdtrav, "serve", "--model", str(model), "--precision", "fp32", "-l", f"tcp/127.0.0.1:{link_port}",
             "--no-multicast-scouting"], env=env, **quiet,
        )  # fmt: skip
        wait_for_port(link_port)  # the relay's link session needs the service listening
        relay = subprocess.Popen(
            [*gcdtrav, "relay", "--camera", "robot/camera", "--source", "r1/front", "--local-connect",
             f"tcp/127.0.0.1:{robot_port}", "-m", "client", "-e", f"tcp/127.0.0.1:{link_port}",
             "--no-multicast-scouting"], env=env, **quiet,
        )  # fmt: skip
        try:
            time.sleep(15)  # the service's start, the relay's first credits
            cpu_before, began = cpu_seconds(relay.pid), time.monotonic()
            samples = []
            while time.monotonic() - began < args.seconds:
                time.sleep(1)
                samples.append(rss_mb(relay.pid))
            cpu = (cpu_seconds(relay.pid) - cpu_before) / (time.monotonic() - began)
        except FileNotFoundError:
            raise SystemExit("the relay exited early:\n" + (Path(scratch) / "log").read_text()[-2000:]) from None
        finally:
            stop.set()
            for process in (relay, service):
                process.terminate()
                process.wait(10)
    print(f"CPU {cpu_name()}: gcdtrav relay at {args.fps:g} fps of 1920x1200 rgb8 ({6.9 * args.fps:.0f} MB/s in)")
    print(f"relay CPU {cpu * 100:.0f} % of one core; RSS median {np.median(samples):.0f} MB, max {max(samples):.0f} MB")


if __name__ == "__main__":
    main()
