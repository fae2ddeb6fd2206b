"""The zenoh relay's robot side owns the speed mask's freshness too: `gcdtrav relay` (a child process, the robot's
zenoh bus behind its own router) against a real `gcdtrav serve` (tiny random model) that is killed with SIGKILL.

The robot's consumer of ``gcdtrav/out/r1/front/grid/speed_mask`` on the robot's bus gets live masks, then, within
``after_s`` + 0.5 s of the last sign of the service, the relay's safe mask (the floor everywhere, centred on the
pose the robot puts on its bus as an Odometry's CDR, as rmw_zenoh carries it), and live masks again from a new
service. Before this round the relay did not bring the mask to the robot's bus at all.
"""

from __future__ import annotations

import contextlib
import signal
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from conftest import textured_image
from zenoh_helpers import (
    client_config,
    free_port,
    listening,
    serve_args,
    start_router,
    subscribed_elsewhere,
    wait_until,
)

pytest.importorskip("torch")

from gcdtrav.schemas.images import encode_jpeg
from gcdtrav.schemas.messages import ImageEnvelope, PixelEncoding, Pose2D
from gcdtrav.schemas.ros_nav import occupancy_grid_geometry

from tools.ros2_robot import NO_SHM, LogFile, relay_command, relayed_service_yaml, stop_process

SOURCE, CAMERA_KEY = "r1/front", "robot/r1/front/jpeg"
POSE_KEY, ODOMETRY_KEY = "robot/r1/pose", "0/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_test"
MASK_KEY = f"gcdtrav/out/{SOURCE}/grid/speed_mask"
FLOOR, AFTER_S, SLACK_S = 0.4, 1.5, 0.5
SERVICE_SETTINGS = relayed_service_yaml(
    SOURCE,
    "intrinsics: {fx: 200, fy: 200, cx: 160, cy: 120, width: 320, height: 240}",
    f"speed: {{floor: {FLOOR}, rate_hz: 10.0}}",
)


def odometry_cdr(x: float, stamp: float) -> bytes:
    """A nav_msgs/Odometry CDR in odom at (x, 0), yaw 0, as the robot's rmw_zenoh puts it."""
    import struct

    sec = int(stamp)
    head = struct.pack("<iI", sec, int((stamp - sec) * 1e9))
    frame, child = b"odom\x00", b"base_link\x00"
    body = head + struct.pack("<I", len(frame)) + frame
    body += bytes(-len(body) % 4) + struct.pack("<I", len(child)) + child
    body += bytes(-len(body) % 8) + struct.pack("<7d", x, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0) + bytes(36 * 8 + 48 + 36 * 8)
    return b"\x00\x01\x00\x00" + body


class Robot:
    """The robot's bus: a camera, odometry (to the robot's bus as CDR, and to the service as its grid's pose
    stream), and the consumer of the speed mask."""

    def __init__(self, bus: zenoh.Session, service_port: int) -> None:
        self.bus = bus
        self.masks: list[tuple[float, Any, bool]] = []  # arrival, geometry, the relay's safe mask
        self.x = 0.0
        self._poses = zenoh.open(client_config(service_port))
        self._stop = threading.Event()
        bus.declare_subscriber(MASK_KEY, self._on_mask)
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _on_mask(self, sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        geometry = occupancy_grid_geometry(payload)
        values = np.frombuffer(payload[-geometry.width * geometry.height :], np.int8)
        safe = geometry.resolution == 1.0
        assert not safe or set(values.tolist()) == {round(FLOOR * 100)}
        self.masks.append((time.time(), geometry, safe))

    def _run(self) -> None:
        jpeg = encode_jpeg(textured_image(240, 320))
        began = time.monotonic()
        while not self._stop.wait(0.1):
            now = time.time()
            self.x = 0.5 * (time.monotonic() - began)
            envelope = ImageEnvelope(stamp=now, encoding=PixelEncoding.JPEG, width=320, height=240, data=jpeg)
            self.bus.put(CAMERA_KEY, envelope.pack())
            self.bus.put(ODOMETRY_KEY, odometry_cdr(self.x, now))
            with contextlib.suppress(zenoh.ZError):  # the service is gone: its grid's poses with it
                self._poses.put(POSE_KEY, Pose2D(stamp=now, frame_id="odom", x=self.x, y=0.0, yaw=0.0).pack())

    def live_since(self, moment: float) -> int:
        return sum(1 for arrived, _, safe in self.masks if not safe and arrived > moment)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self._poses.close()


def serve(model: Path, settings: Path, port: int, log: LogFile) -> subprocess.Popen[Any]:
    arguments = ["--settings", str(settings), "--state-dir", str(settings.parent), "--precision", "fp32"]
    return subprocess.Popen(
        serve_args(model, *arguments, "--cfg", NO_SHM, "-l", f"tcp/127.0.0.1:{port}"),
        stdout=subprocess.DEVNULL,
        stderr=log.handle,
    )


def test_the_zenoh_relay_puts_the_safe_mask_on_the_robots_bus_when_the_service_dies(
    tiny_model_dir: Path, tmp_path: Path
) -> None:
    settings = tmp_path / "service.yaml"
    settings.write_text(SERVICE_SETTINGS)
    service_port, robot_port = free_port(), free_port()
    router = start_router(robot_port)
    service_log, relay_log = LogFile(tmp_path / "serve.log"), LogFile(tmp_path / "relay.log")
    service = serve(tiny_model_dir, settings, service_port, service_log)
    bus = zenoh.open(client_config(robot_port))
    relay = None
    try:
        assert wait_until(lambda: listening(service_port), 60), service_log.text()
        relay = subprocess.Popen(
            relay_command(
                *("--camera", CAMERA_KEY, "--source", SOURCE, "-e", f"tcp/127.0.0.1:{service_port}"),
                *("--local-connect", f"tcp/127.0.0.1:{robot_port}", "--pose-key", "0/odom/**", "--cfg", NO_SHM),
                *("--safe-after", str(AFTER_S), "--safe-floor", str(FLOOR), "--max-speed", "1.0"),
            ),
            stdout=subprocess.DEVNULL,
            stderr=relay_log.handle,
        )
        assert subscribed_elsewhere(bus, CAMERA_KEY, 60), relay_log.text()
        robot = Robot(bus, service_port)
        try:
            logs = lambda: f"relay:\n{relay_log.text()[-3000:]}\nservice:\n{service_log.text()[-2000:]}"  # noqa: E731
            assert wait_until(lambda: robot.live_since(0.0) >= 3, 120), logs()
            service.send_signal(signal.SIGKILL)
            killed_at = time.time()
            service.wait(10)
            assert wait_until(lambda: any(safe for _, _, safe in robot.masks), AFTER_S + 10), logs()
            safe_at, safe, _ = next(mask for mask in robot.masks if mask[2])
            last_live = max(arrived for arrived, _, is_safe in robot.masks if not is_safe and arrived <= killed_at)
            assert safe_at - last_live <= AFTER_S + SLACK_S + 0.5, (safe_at - last_live, logs())  # + 1/10 Hz masks
            centre = safe.origin[0] + safe.width * safe.resolution / 2
            assert safe.frame_id == "odom" and abs(centre - robot.x) < 2.0  # around the robot, from its odometry
            assert safe.width * safe.resolution == pytest.approx(4 * 1.0 * 30.0)  # 2 x max speed x horizon each way
            back_at = time.time()
            service = serve(tiny_model_dir, settings, service_port, service_log)
            assert wait_until(lambda: robot.live_since(back_at) >= 2, 120), logs()
        finally:
            robot.close()
    finally:
        if relay is not None:
            assert stop_process(relay) == 0, relay_log.text()[-2000:]
        stop_process(service)
        bus.close()
        stop_process(router)
    assert "Traceback" not in relay_log.text()
