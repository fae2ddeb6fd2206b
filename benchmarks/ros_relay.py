"""What crosses the link with `gcdtrav relay --ros`, against a raw bridge: a 1280 x 720 rgb8 camera at 15 Hz
(sensor_msgs/Image, 2.76 MB a frame), its CameraInfo and 30 Hz odometry, published by real rclpy nodes over
Fast DDS on loopback; the relay node (a child process, as on a robot) sends them to a service on loopback
zenoh; ROS subscribers on the robot take T, U and the Nav2 costmap back.

Measured: the link's bytes each way (zenoh subscribers on the service's side count every key the relay puts
and every output key it fetches), per camera frame published, and the end-to-end latency from a camera
frame's publish to the costmap (and to T) stamped with it received on the robot. A raw bridge
(zenoh-bridge-ros2dds, or rmw_zenoh to an offboard router) forwards every message: size x rate.

The model is random weights at CLIPSeg's 352 x 352 input (tiny preset: the link's bytes are the real model's,
its compute is not; ``--model DIR`` for a checkpoint), so latency here is the link's and the relay's, not
a CPU's inference.

    python -m benchmarks.ros_relay [--seconds 30] [--fps 15] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import random
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.backends.cpus import cpu_name

from tools.loopback import in_process_service
from tools.random_clipseg import save_random_clipseg
from tools.ros2_robot import Camera, LogFile, Odometry, RosRobot, relay_command, ros_environment, stamp_of, stop_process

SOURCE = "r1/front"
TOPIC = "/r1/front/image_raw"


def scene(height: int, width: int) -> np.ndarray:
    """A camera-like picture: smooth ground and sky, a few objects, sensor noise (JPEG sizes like a scene's)."""
    rng = np.random.default_rng(0)
    y = np.mgrid[0:height, 0:width][0].astype(np.float32)
    image = np.stack([90 + 60 * y / height, 110 + 40 * y / height, 150 - 70 * y / height], axis=2)
    for _ in range(12):
        top, left = rng.integers(height // 3, height - 60), rng.integers(0, width - 120)
        image[top : top + rng.integers(20, 120), left : left + rng.integers(30, 200)] = rng.integers(20, 230, 3)
    image += rng.normal(0, 4, image.shape)
    return np.clip(image, 0, 255).astype(np.uint8)


def service_settings(state_dir: Path) -> ServiceSettings:
    return ServiceSettings.model_validate(
        {
            "state_dir": state_dir,
            "instance": "bench",
            "preview": False,
            "reuse": {"enabled": False},  # every frame inferred and fused: the costmap follows each one
            "grids": [
                {
                    "source": SOURCE,
                    "camera_info_key": "robot/r1/front/camera_info",
                    "mount": {"z": 1.0, "pitch": 0.5},
                    "size_m": 16.0,
                    "resolution_m": 0.2,
                    "pose_key": "robot/r1/pose",
                    "costmap": True,
                }
            ],
        }
    )


class LinkMeter:
    """Bytes and messages per key group, counted where the link ends at the service."""

    def __init__(self, session: zenoh.Session) -> None:
        self.bytes: Counter[str] = Counter()
        self.messages: Counter[str] = Counter()
        self.counting = False
        self._lock = threading.Lock()
        groups = {
            "up: camera frames (JPEG envelopes)": f"gcdtrav/in/{SOURCE}",
            "up: CameraInfo (CDR)": "robot/r1/front/camera_info",
            "up: odometry (Pose2D)": "robot/r1/pose",
            "down: maps8 (T, U)": f"gcdtrav/out/{SOURCE}/maps8",
            "down: costmap (OccupancyGrid CDR)": f"gcdtrav/out/{SOURCE}/grid/costmap",
        }
        self._subscribers = [session.declare_subscriber(key, self._counter(name)) for name, key in groups.items()]

    def _counter(self, name: str) -> Any:
        def count(sample: zenoh.Sample) -> None:
            if self.counting:
                with self._lock:
                    self.bytes[name] += len(sample.payload)
                    self.messages[name] += 1

        return count


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def run(args: argparse.Namespace, scratch: Path) -> dict[str, Any]:
    from gcdtrav.service.backends.clipseg import ClipSegBackend
    from nav_msgs.msg import OccupancyGrid
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    model = args.model or str(save_random_clipseg(scratch / "tiny", preset="tiny", input_size=352))
    backend = ClipSegBackend(model)
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    with in_process_service(backend, service_settings(scratch / "state")) as (service, port):
        meter = LinkMeter(service.session)
        robot = RosRobot("bench_robot")
        camera = Camera(robot, TOPIC, scene(720, 1280), args.fps, frame_id="front_optical", focal=900.0, qos=1)
        odometry = Odometry(robot, "/r1/odom", 30.0)
        log = LogFile(scratch / "relay.log")
        relay = subprocess.Popen(
            relay_command(
                "--ros",
                "-e",
                f"tcp/127.0.0.1:{port}",
                "--ros-args",
                "-p",
                f"camera:={TOPIC}",
                "-p",
                f"source:={SOURCE}",
                "-p",
                "camera_info_key:=robot/r1/front/camera_info",
                "-p",
                "odometry_topic:=/r1/odom",
                "-p",
                "odometry_key:=robot/r1/pose",
            ),
            stdout=subprocess.DEVNULL,
            stderr=log.handle,
        )
        try:
            _, traversability = robot.subscribe(Image, f"{TOPIC}/gcdtrav/traversability")
            _, costmap = robot.subscribe(OccupancyGrid, f"{TOPIC}/gcdtrav/grid/costmap", latched)
            deadline = time.monotonic() + 180
            while len(costmap) < 3 and time.monotonic() < deadline:
                time.sleep(0.2)
            if len(costmap) < 3:
                raise RuntimeError(f"no costmap within 180 s: {log.text()[-2000:]}")
            frames_before, costmaps_before, maps_before = len(camera.stamps), len(costmap), len(traversability)
            meter.counting = True
            began = time.monotonic()
            load_before = os.getloadavg()
            time.sleep(args.seconds)
            meter.counting = False
            elapsed = time.monotonic() - began
            frames = len(camera.stamps) - frames_before
            costmap_latency = [
                received - camera.published_at[stamp_of(grid)]
                for grid, received in costmap.messages[costmaps_before:]
                if stamp_of(grid) in camera.published_at
            ]
            maps_latency = [
                received - camera.published_at[stamp_of(image)]
                for image, received in traversability.messages[maps_before:]
                if stamp_of(image) in camera.published_at
            ]
        finally:
            stop_process(relay)
            camera.stop()
            odometry.stop()
            robot.close()
    frame_bytes = len(bytes(camera.message.data)) + 60  # the CDR: pixels, header, encoding, sizes
    up = sum(b for name, b in meter.bytes.items() if name.startswith("up"))
    down = sum(b for name, b in meter.bytes.items() if name.startswith("down"))
    return {
        "cpu": cpu_name(),
        "load_average_1_5_15": [round(v, 2) for v in load_before],
        "seconds": round(elapsed, 1),
        "camera": f"1280x720 rgb8 sensor_msgs/Image at {args.fps:g} Hz",
        "camera_frames": frames,
        "frames_sent": meter.messages["up: camera frames (JPEG envelopes)"],
        "costmaps_received": len(costmap_latency),
        "raw_bridge_bytes_per_s": frame_bytes * frames / elapsed,
        "link_up_bytes_per_s": up / elapsed,
        "link_down_bytes_per_s": down / elapsed,
        "link_bytes_per_camera_frame": (up + down) / max(frames, 1),
        "link_share_of_raw": (up + down) / max(frame_bytes * frames, 1),
        "by_key": {
            name: {"bytes_per_s": b / elapsed, "messages": meter.messages[name]} for name, b in meter.bytes.items()
        },
        "jpeg_bytes_mean": meter.bytes["up: camera frames (JPEG envelopes)"]
        / max(meter.messages["up: camera frames (JPEG envelopes)"], 1),
        "latency_costmap_s": {
            "median": statistics.median(costmap_latency),
            "p95": percentile(costmap_latency, 0.95),
        }
        if costmap_latency
        else None,
        "latency_maps_s": {"median": statistics.median(maps_latency), "p95": percentile(maps_latency, 0.95)}
        if maps_latency
        else None,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=30.0, help="measured window after the first costmaps")
    parser.add_argument("--fps", type=float, default=15.0, help="camera rate")
    parser.add_argument("--model", help="a CLIPSeg checkpoint (default: random weights, tiny, 352 input)")
    parser.add_argument("--domain", type=int, default=random.randint(100, 200), help="ROS_DOMAIN_ID")
    parser.add_argument("--json", type=Path, help="write the result here too")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="gcdtrav-ros-relay-") as scratch, ros_environment(args.domain):
        result = run(args, Path(scratch))
    text = json.dumps(result, indent=2)
    print(text)
    if args.json is not None:
        args.json.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
