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
from zenoh_helpers import connecting_config, free_port, subscribed_elsewhere, wait_until

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
    link: zenoh.Session  # the relay's session to the service
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
            yield Robot(bus, link, relay, camera, service_client, changes, service)
        finally:
            camera.stop()
            relay.close()
            service_client.close()
            for session in (local, link, bus):
                session.close()


def link_ready(robot: Robot) -> None:
    """Each side's subscriptions known where the other publishes: the relay's camera subscription on the
    robot's bus, the service's input subscription on the relay's link, the relay's credit subscription on the
    service. A first frame sent before would be lost, and its credit with it (a credit timeout)."""
    assert subscribed_elsewhere(robot.bus, CAMERA_KEY), "the relay's camera subscription"
    assert subscribed_elsewhere(robot.link, f"gcdtrav/in/{SOURCE}"), "the service's input subscription"
    assert subscribed_elsewhere(robot.service.session, Keys().credit(SOURCE)), "the relay's credit subscription"


def source_status(robot: Robot):  # type: ignore[no-untyped-def]
    return robot.service_client.status().sources.get(SOURCE)


def test_relay_sends_only_when_the_service_is_ready(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    # Every credit comes: no frame may go on a timeout. 10 s, not the default 1.5 s: on a loaded 2-core machine
    # the slow service's first answers (0.3 s a frame here, and the first inference) can take longer than that.
    with robot_with_relay(tiny_backend, tmp_path, credit_timeout_s=10.0) as robot:
        maps: list[Maps] = []
        health: list[RelayHealth] = []
        consumer = robot.bus.declare_subscriber(
            f"gcdtrav/out/{SOURCE}/maps8", lambda s: maps.append(Maps.from_compact_payload(s.payload.to_bytes()))
        )
        watcher = robot.bus.declare_subscriber(
            f"gcdtrav/relay/{SOURCE}/health", lambda s: health.append(RelayHealth.unpack(s.payload.to_bytes()))
        )
        forwarders = {f.kind: f for f in robot.relay.forwarders}
        assert wait_until(lambda: forwarders["maps8"].active, 30), "the consumer's subscription was not seen"
        link_ready(robot)
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
        assert wait_until(lambda: bool(health) and health[-1].frames_sent > 0 and health[-1].map_age_s is not None, 30)
        latest = health[-1]
        assert latest.owner == "box-1" and not latest.stale and latest.uplink_bytes_per_s > 0
        assert latest.clock_offset_s is not None and abs(latest.clock_offset_s) < 1.0  # one clock here

        # Frames captured 10 s ago are stale: dropped and counted, and the credit comes back at once.
        robot.camera.age_s = 10.0
        assert wait_until(lambda: (source_status(robot).stale or 0) >= 3, 30), "stale frames not counted"
        assert camera.window.timeouts == 0
        robot.camera.age_s = 0.0
        before = len(maps)
        assert wait_until(lambda: len(maps) > before, 30), "no fresh maps after the stale frames"

        # The camera stops: the maps age, the relay says so.
        robot.camera.stop()
        assert wait_until(lambda: any(c.stale for c in robot.changes), 30), "staleness not reported"
        assert wait_until(lambda: health[-1].stale, 30)
        consumer.undeclare()
        assert wait_until(lambda: not forwarders["maps8"].active, 30), "forwarding went on without a consumer"
        watcher.undeclare()


def test_a_lost_credit_costs_one_timeout(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    """Credits that never come (a service of another prefix grants them elsewhere): the relay sends a frame
    per timeout, no more."""
    with robot_with_relay(tiny_backend, tmp_path, prefix="elsewhere", credit_timeout_s=0.5) as robot:
        robot.camera.start()
        camera = robot.relay.camera(SOURCE)
        assert wait_until(lambda: camera.window.timeouts >= 2, 30)
        # One frame per timeout (the camera offers 50 a second): n frames sent span at least n - 1 timeouts.
        # Timed around the counts (the clock read before the first and after the second), so that a frame
        # sent between a count and the clock is inside the measured span.
        started = time.monotonic()
        sent = camera.sent
        assert wait_until(lambda: camera.sent >= sent + 3, 30)
        more = camera.sent - sent
        elapsed = time.monotonic() - started
        assert elapsed >= (more - 1) * 0.5 - 0.01, (more, elapsed)  # 10 ms: float rounding of the two clocks
        with camera._cond:  # counted together under the sender's lock
            timeouts, sent = camera.window.timeouts, camera.sent
        assert timeouts == sent - 1  # every frame but the first went on a timeout
        assert wait_until(lambda: source_status(robot) is not None, 30)  # the frames still arrive
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
        assert wait_until(lambda: health().map_age_s is not None and not health().stale, 30), health()
        assert wait_until(lambda: "camera_clock" in health().causes, 30)
        assert "3600" in health().causes["camera_clock"] and "behind" in health().causes["camera_clock"]
        assert set(health().causes) == {"camera_clock"}
        reports: list[RelayHealth] = []
        watcher = robot.bus.declare_subscriber(
            f"gcdtrav/relay/{SOURCE}/health", lambda s: reports.append(RelayHealth.unpack(s.payload.to_bytes()))
        )
        robot.camera.stop()
        assert wait_until(lambda: "camera_silent" in health().causes, 30), health()
        assert CAMERA_KEY in health().causes["camera_silent"]
        # Five more health reports that name it: still one line for the change. A report is published, then its
        # causes logged: the first that names it logged the line, and the seventh's arrival proves the sixth's
        # logging done.
        silent = lambda: sum("camera_silent" in report.causes for report in reports)  # noqa: E731
        assert wait_until(lambda: silent() >= 7, 30), reports[-1:]
        watcher.undeclare()
        named = [r for r in caplog.records if "camera_silent" in r.getMessage()]
        assert len(named) == 1, [r.getMessage() for r in named]


def test_a_parked_camera_is_no_cause_and_the_service_hears_it_over_the_link(  # type: ignore[no-untyped-def]
    tiny_backend, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The robot's software parks the camera and stops it: the relay names no silent camera and says parked, on
    its bus and over the link, where the service hears it (the silent-robot alert's gcdtrav_source_parked);
    running again, the silence is a cause again."""
    caplog.set_level(logging.INFO, logger="gcdtrav.relay")
    with robot_with_relay(tiny_backend, tmp_path, camera_silent_after_s=0.5, link_health_period_s=0.5) as robot:
        heard = lambda: robot.service.runtime.presence.heard().get(SOURCE)  # noqa: E731
        health = lambda: robot.relay.health(SOURCE)  # noqa: E731
        camera = robot.relay.camera(SOURCE)
        robot.camera.start()
        assert wait_until(lambda: heard() is not None and heard().parked is False, 30), heard()  # over the link
        parked_key = Keys().relay_parked(SOURCE)
        assert subscribed_elsewhere(robot.bus, parked_key), "the relay's parked subscription"
        robot.bus.put(parked_key, CameraParked(parked=True, reason="charging").pack())
        robot.camera.stop()
        assert wait_until(lambda: heard().parked is True, 30), heard()  # told at once, not at the next period
        # silent twice camera_silent_after_s, as the relay sees it (its last frame may have come after the stop)
        assert wait_until(lambda: time.time() - (camera.last_frame_at or 0.0) > 1.0, 30)
        assert health().parked and "camera_silent" not in health().causes, health()
        # silent at the service all the same (its last frame came when a credit let it go): only parked keeps
        # the alert quiet
        assert wait_until(lambda: time.time() - heard().last_frame_at > 0.9, 30), heard()
        assert heard().parked is True
        robot.bus.put(parked_key, b'{"parked": false}')  # JSON, as a shell script would say it
        assert wait_until(lambda: heard().parked is False and "camera_silent" in health().causes, 30), health()
        robot.bus.put(parked_key, b"not a message")  # ignored, logged
        ignored = lambda: any("ignoring a parked notice" in r.getMessage() for r in caplog.records)  # noqa: E731
        assert wait_until(ignored, 30), "the bad notice was not judged"
        assert heard().parked is False and not health().parked


def test_a_refusing_service_is_named_in_the_relays_health(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    with robot_with_relay(tiny_backend, tmp_path, service_kw={"max_pixels": 100}) as robot:
        robot.camera.start()
        causes = lambda: robot.relay.health(SOURCE).causes  # noqa: E731
        assert wait_until(lambda: "service_refuses" in causes(), 30), causes()
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
