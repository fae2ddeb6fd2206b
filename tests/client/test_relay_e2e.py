"""`gcdtrav relay` end to end on loopback: a robot bus with a fast camera, the relay, a slow service.

Three zenoh sessions as on a real robot: the robot's bus (a peer the camera and the robot's consumers use),
the relay's two sessions (robot side, link side), and the service's. Asserted: the relay sends a frame only
when the service is ready for it (at most one inferred and one waiting), maps come back to the robot's bus
only because a consumer there subscribes, stale frames are counted, and the relay says when maps go stale.
"""

from __future__ import annotations

import logging
import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from conftest import TINY_INPUT_SIZE, textured_image, torch_free_gcdtrav
from zenoh_helpers import connecting_config, free_port, wait_until

pytest.importorskip("torch")

from gcdtrav.client import Maps, TraversabilityClient
from gcdtrav.client.freshness import Staleness
from gcdtrav.client.relay.relay import Relay
from gcdtrav.client.session.zenoh_args import zenoh_config
from gcdtrav.schemas.images import encode_jpeg
from gcdtrav.schemas.keys import Keys
from gcdtrav.schemas.messages import CameraParked, ImageEnvelope, PixelEncoding, RelayHealth
from gcdtrav.schemas.relay import RelaySettings
from gcdtrav.schemas.settings import ServiceSettings

from tools.loopback import in_process_service

CAMERA_KEY = "robot/camera/front"
SOURCE = "r1/front"


class SlowBackend:
    """A CPU box slower than the camera: every frame takes ``delay`` more."""

    def __init__(self, inner, delay: float) -> None:  # type: ignore[no-untyped-def]
        self.inner, self.delay, self.model_id = inner, delay, inner.model_id

    def describe(self):  # type: ignore[no-untyped-def]
        return self.inner.describe()

    def prepare(self, concepts):  # type: ignore[no-untyped-def]
        return self.inner.prepare(concepts)

    def logits(self, image, prepared):  # type: ignore[no-untyped-def]
        time.sleep(self.delay)
        return self.inner.logits(image, prepared)


class Camera:
    """Publishes 320x240 JPEG envelopes on the robot's bus as fast as it can (about 50/s), stamped now less
    ``age_s``."""

    def __init__(self, session: zenoh.Session) -> None:
        self.publisher = session.declare_publisher(CAMERA_KEY)
        self.data = encode_jpeg(textured_image(240, 320))
        self.age_s = 0.0
        self.sent = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(0.02):
            envelope = ImageEnvelope(
                stamp=time.time() - self.age_s, encoding=PixelEncoding.JPEG, width=320, height=240, data=self.data
            )
            self.publisher.put(envelope.pack())
            self.sent += 1

    def start(self) -> Camera:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5)


@dataclass
class Robot:
    bus: zenoh.Session  # the robot's own bus: camera, consumers
    relay: Relay
    camera: Camera
    service_client: TraversabilityClient
    changes: list[Staleness]
    service: Any  # the TraversabilityService, in this process


@contextmanager
def robot_with_relay(
    tiny_backend, tmp_path: Path, service_kw: dict[str, object] | None = None, **relay_kw: object
) -> Iterator[Robot]:  # type: ignore[no-untyped-def]
    settings = ServiceSettings.model_validate(
        {"state_dir": tmp_path, "instance": "box-1", "preview": False, "max_frame_age_s": 2.0} | (service_kw or {})
    )
    with in_process_service(SlowBackend(tiny_backend, 0.3), settings) as (service, service_port):
        robot_port = free_port()
        bus = zenoh.open(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{robot_port}"], multicast_scouting=False))
        link = zenoh.open(connecting_config(service_port, mode="client"))
        local = zenoh.open(connecting_config(robot_port, mode="client"))
        service_client = TraversabilityClient(config=connecting_config(service_port), timeout=5.0)
        relay_settings = RelaySettings.model_validate(
            {"cameras": [{"camera": CAMERA_KEY, "source": SOURCE}], "stale_after_s": 1.0, "health_period_s": 0.2}
            | relay_kw
        )
        changes: list[Staleness] = []
        relay = Relay(relay_settings, link, local, on_stale=changes.append).start()
        camera = Camera(bus)
        try:
            yield Robot(bus, relay, camera, service_client, changes, service)
        finally:
            camera.stop()
            relay.close()
            service_client.close()
            for session in (local, link, bus):
                session.close()


def source_status(robot: Robot):  # type: ignore[no-untyped-def]
    return robot.service_client.status().sources.get(SOURCE)


def test_relay_sends_only_when_the_service_is_ready(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    with robot_with_relay(tiny_backend, tmp_path) as robot:
        maps: list[Maps] = []
        health: list[RelayHealth] = []
        consumer = robot.bus.declare_subscriber(
            f"gcdtrav/out/{SOURCE}/maps8", lambda s: maps.append(Maps.from_compact_payload(s.payload.to_bytes()))
        )
        watcher = robot.bus.declare_subscriber(
            f"gcdtrav/relay/{SOURCE}/health", lambda s: health.append(RelayHealth.unpack(s.payload.to_bytes()))
        )
        forwarders = {f.kind: f for f in robot.relay.forwarders}
        assert wait_until(lambda: forwarders["maps8"].active, 10), "the consumer's subscription was not seen"
        robot.camera.start()
        assert wait_until(lambda: len(maps) >= 4, 30), "no maps on the robot's bus"

        # Only the subscribed form crosses the link; the frames went at the model's size (96 x 96 here).
        assert not forwarders["maps"].active and not forwarders["preview"].active
        first, last = maps[0], maps[-1]
        assert first.compact and first.header.source == SOURCE and first.header.instance == "box-1"
        assert first.header.image_size == last.header.image_size == (320, 240)  # the camera's pixels, though
        assert robot.relay.camera(SOURCE).model_input == (TINY_INPUT_SIZE, TINY_INPUT_SIZE)  # shrunk to 128x96
        assert first.traversability.shape == first.header.map_shape == (TINY_INPUT_SIZE, TINY_INPUT_SIZE)
        assert first.traversability.min() >= 0.0 and first.traversability.max() <= 1.0
        assert first.age_s < 10

        # At most one frame inferred and one waiting: every frame sent is processed (or answered with the
        # last maps, its view unchanged), or about to be.
        camera = robot.relay.camera(SOURCE)
        status = source_status(robot)
        assert status is not None
        assert camera.sent <= status.processed + status.unchanged + 3, (camera.sent, status)
        assert camera.captured > camera.sent  # the camera is faster: the relay kept only the newest
        assert camera.window.timeouts == 0 and status.credits >= status.processed
        assert status.frame_age_ms and status.bytes_per_s is not None and status.stale == 0

        # Health on the robot's bus: fresh maps, the owner, the link's figures.
        assert wait_until(lambda: bool(health) and health[-1].frames_sent > 0 and health[-1].map_age_s is not None)
        latest = health[-1]
        assert latest.owner == "box-1" and not latest.stale and latest.uplink_bytes_per_s > 0
        assert latest.clock_offset_s is not None and abs(latest.clock_offset_s) < 1.0  # one clock here

        # Frames captured 10 s ago are stale: dropped and counted, and the credit comes back at once.
        robot.camera.age_s = 10.0
        assert wait_until(lambda: (source_status(robot).stale or 0) >= 3, 20), "stale frames not counted"
        assert camera.window.timeouts == 0
        robot.camera.age_s = 0.0
        before = len(maps)
        assert wait_until(lambda: len(maps) > before, 20), "no fresh maps after the stale frames"

        # The camera stops: the maps age, the relay says so.
        robot.camera.stop()
        assert wait_until(lambda: any(c.stale for c in robot.changes), 10), "staleness not reported"
        assert wait_until(lambda: health[-1].stale, 5)
        consumer.undeclare()
        assert wait_until(lambda: not forwarders["maps8"].active, 10), "forwarding went on without a consumer"
        watcher.undeclare()


def test_a_lost_credit_costs_one_timeout(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    """Credits that never come (a service of another prefix grants them elsewhere): the relay sends a frame
    per timeout, no more."""
    with robot_with_relay(tiny_backend, tmp_path, prefix="elsewhere", credit_timeout_s=0.5) as robot:
        robot.camera.start()
        camera = robot.relay.camera(SOURCE)
        assert wait_until(lambda: camera.window.timeouts >= 2, 10)
        time.sleep(1.0)
        elapsed = time.monotonic()
        sent = camera.sent
        time.sleep(1.0)
        elapsed = time.monotonic() - elapsed
        assert camera.sent - sent <= elapsed / 0.5 + 1  # one per timeout (the camera offers 50 a second)
        assert wait_until(lambda: source_status(robot) is not None, 10)  # the frames still arrive
        causes = robot.relay.health(SOURCE).causes  # the relay says why maps stay away
        assert "no_instance" in causes and "'elsewhere'" in causes["no_instance"], causes


def test_a_camera_on_another_clock_is_not_stale_and_a_silent_camera_is_named_once(  # type: ignore[no-untyped-def]
    tiny_backend, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Every frame stamped an hour ago (a camera on another clock): the service judges by delay and serves them,
    and so does the relay: fresh, with the clock named. Then the camera stops: named, and logged once."""
    caplog.set_level(logging.INFO, logger="gcdtrav.relay")
    with robot_with_relay(tiny_backend, tmp_path, camera_silent_after_s=0.5) as robot:
        robot.camera.age_s = 3600.0
        robot.camera.start()
        health = lambda: robot.relay.health(SOURCE)  # noqa: E731
        assert wait_until(lambda: health().map_age_s is not None and not health().stale, 20), health()
        assert wait_until(lambda: "camera_clock" in health().causes, 5)
        assert "3600" in health().causes["camera_clock"] and "behind" in health().causes["camera_clock"]
        assert set(health().causes) == {"camera_clock"}
        robot.camera.stop()
        assert wait_until(lambda: "camera_silent" in health().causes, 5), health()
        assert CAMERA_KEY in health().causes["camera_silent"]
        time.sleep(1.0)  # five health periods: still one line for the change
        named = [r for r in caplog.records if "camera_silent" in r.getMessage()]
        assert len(named) == 1, [r.getMessage() for r in named]


def test_a_parked_camera_is_no_cause_and_the_service_hears_it_over_the_link(  # type: ignore[no-untyped-def]
    tiny_backend, tmp_path: Path
) -> None:
    """The robot's software parks the camera and stops it: the relay names no silent camera and says parked, on
    its bus and over the link, where the service hears it (the silent-robot alert's gcdtrav_source_parked);
    running again, the silence is a cause again."""
    with robot_with_relay(tiny_backend, tmp_path, camera_silent_after_s=0.5, link_health_period_s=0.5) as robot:
        heard = lambda: robot.service.runtime.presence.heard().get(SOURCE)  # noqa: E731
        health = lambda: robot.relay.health(SOURCE)  # noqa: E731
        robot.camera.start()
        assert wait_until(lambda: heard() is not None and heard().parked is False, 20), heard()  # over the link
        parked_key = Keys().relay_parked(SOURCE)
        robot.bus.put(parked_key, CameraParked(parked=True, reason="charging").pack())
        robot.camera.stop()
        assert wait_until(lambda: heard().parked is True, 5), heard()  # told at once, not at the next period
        time.sleep(1.0)  # twice camera_silent_after_s
        assert health().parked and "camera_silent" not in health().causes, health()
        last_frame = heard().last_frame_at
        assert time.time() - last_frame > 0.9  # silent all the same: only parked keeps the alert quiet
        robot.bus.put(parked_key, b'{"parked": false}')  # JSON, as a shell script would say it
        assert wait_until(lambda: heard().parked is False and "camera_silent" in health().causes, 5), health()
        robot.bus.put(parked_key, b"not a message")  # ignored, logged
        time.sleep(0.6)
        assert heard().parked is False and not health().parked


def test_a_refusing_service_is_named_in_the_relays_health(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    with robot_with_relay(tiny_backend, tmp_path, service_kw={"max_pixels": 100}) as robot:
        robot.camera.start()
        causes = lambda: robot.relay.health(SOURCE).causes  # noqa: E731
        assert wait_until(lambda: "service_refuses" in causes(), 20), causes()
        assert "too_many_pixels" in causes()["service_refuses"] and "no_instance" not in causes()


def test_relay_command_is_torch_free_and_checks_its_arguments() -> None:
    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(torch_free_gcdtrav("relay", *args), capture_output=True, text=True, timeout=60)

    unpaired = run("--camera", "a", "--camera", "b", "--source", "r1/a")
    assert unpaired.returncode == 2 and "2 --camera but 1 --source" in unpaired.stderr
    nothing = run()
    assert nothing.returncode == 2 and "cameras" in nothing.stderr and "Traceback" not in nothing.stderr
    bad = run("--camera", "a", "--source", "r/*")
    assert bad.returncode == 2 and "literal zenoh key" in bad.stderr


def test_frames_shrink_to_the_model_and_keep_their_stamp() -> None:
    """The relay's envelope without a bus: a raw frame from a camera key, shrunk, JPEG, stamp kept."""
    from gcdtrav.client.relay.relay import CameraLink, CapturedFrame
    from gcdtrav.schemas.images import decode_image

    class FakeRelay:
        settings = RelaySettings.model_validate({"cameras": [{"camera": "cam", "source": "s"}], "jpeg_quality": 90})

    link = CameraLink(FakeRelay(), FakeRelay.settings.cameras[0])  # type: ignore[arg-type]
    raw = ImageEnvelope(
        stamp=42.5, frame_id="cam_optical", encoding=PixelEncoding.RGB8, width=1920, height=1200,
        data=np.full((1200, 1920, 3), 90, np.uint8).tobytes(),
    )  # fmt: skip
    frame = CapturedFrame(zenoh.ZBytes(raw.pack()), "application/msgpack", "cam", time.time())
    envelope = link._envelope(frame, (352, 352))
    assert envelope is not None
    assert (envelope.width, envelope.height, envelope.stamp, envelope.frame_id) == (563, 352, 42.5, "cam_optical")
    assert envelope.original_size == (1920, 1200)  # the service answers in the camera's pixels
    assert envelope.encoding is PixelEncoding.JPEG and envelope.sent_at is not None
    assert abs(int(decode_image(envelope.data)[100, 100, 0]) - 90) <= 2
    assert link._envelope(CapturedFrame(zenoh.ZBytes(b"junk"), "image/jpeg", "cam", 0.0), (352, 352)) is None
    assert link.undecodable == 1
