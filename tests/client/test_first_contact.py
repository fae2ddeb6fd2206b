"""A new user's first contact (issue 36), end to end on loopback: the README's examples against a PNG camera,
a JPEG camera and a relayed camera, answers in the camera's own pixels, and a starved source that says why.

Sessions as on a real robot: the robot's bus (camera, consumers), the relay's two sessions, the service's.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

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
from gcdtrav.schemas.images import encode_jpeg, encode_png
from gcdtrav.schemas.messages import ImageEnvelope, PixelEncoding, RelayHealth
from gcdtrav.schemas.relay import RelaySettings
from gcdtrav.schemas.settings import ServiceSettings

from tools.loopback import in_process_service

REPO = Path(__file__).resolve().parents[2]
CAMERA_KEY = "robot/camera/front"
SOURCE = "r1/front"


class Camera:
    """Publishes one image over and over on ``key`` (about 5 frames/s): bare bytes with ``encoding`` (None:
    zenoh's default), or envelopes stamped now less ``age_s``."""

    def __init__(self, session: zenoh.Session, key: str, data: bytes, encoding: str | None, size: tuple[int, int]):
        self.publisher = session.declare_publisher(key)
        self.data, self.encoding, self.size = data, encoding, size
        self.envelope: PixelEncoding | None = None
        self.age_s = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(0.2):
            if self.envelope is None:
                options = {} if self.encoding is None else {"encoding": zenoh.Encoding(self.encoding)}
                self.publisher.put(self.data, **options)
            else:
                envelope = ImageEnvelope(
                    stamp=time.time() - self.age_s, encoding=self.envelope, width=self.size[0], height=self.size[1],
                    data=self.data,
                )  # fmt: skip
                self.publisher.put(envelope.pack(), encoding=zenoh.Encoding("application/msgpack"))

    def start(self) -> Camera:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5)


@dataclass
class Setup:
    port: int  # the service's
    client: TraversabilityClient  # on the service's side
    bus: zenoh.Session  # the robot's
    relay: Relay | None = None
    changes: list[Staleness] = field(default_factory=list)


@contextmanager
def service_and_robot(tiny_backend, tmp_path: Path, relay: dict | None = None, **settings: object) -> Iterator[Setup]:  # type: ignore[no-untyped-def]
    service_settings = ServiceSettings(state_dir=tmp_path, instance="box-1", preview=False, **settings)  # type: ignore[arg-type]
    with in_process_service(tiny_backend, service_settings) as (_, port):
        robot_port = free_port()
        bus = zenoh.open(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{robot_port}"], multicast_scouting=False))
        link = zenoh.open(connecting_config(port, mode="client"))
        local = zenoh.open(connecting_config(robot_port, mode="client"))
        client = TraversabilityClient(config=connecting_config(port), timeout=5.0)
        setup = Setup(port, client, bus)
        if relay is not None:
            relay_settings = RelaySettings.model_validate(
                {"cameras": [{"camera": CAMERA_KEY, "source": SOURCE}], "stale_after_s": 1.0, "health_period_s": 0.2}
                | relay
            )
            setup.relay = Relay(relay_settings, link, local, on_stale=setup.changes.append).start()
        try:
            yield setup
        finally:
            if setup.relay is not None:
                setup.relay.close()
            client.close()
            for session in (local, link, bus):
                session.close()


def maps_of(client: TraversabilityClient, source: str) -> list[Maps]:
    received: list[Maps] = []
    client.subscribe_maps(source, received.append)
    return received


def run_example(port: int, script: str, *args: str) -> subprocess.CompletedProcess[str]:
    """An example as the README runs it, pointed at the loopback service."""
    zenoh_flags = ("-e", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / ".pkg"), os.environ.get("PYTHONPATH", "")])}
    command = [sys.executable, str(REPO / "examples" / script), *args, *zenoh_flags]
    return subprocess.run(command, capture_output=True, text=True, timeout=120, env=env, cwd=REPO)


def gcdtrav(port: int, *args: str) -> subprocess.CompletedProcess[str]:
    zenoh_flags = ("-e", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting")
    return subprocess.run(torch_free_gcdtrav(*args, *zenoh_flags), capture_output=True, text=True, timeout=120)


def expected_patch(x: float, y: float, image_size: tuple[int, int], map_shape: tuple[int, int]) -> tuple[int, int]:
    (width, height), (rows, cols) = image_size, map_shape
    return int(y / (height / rows)), int(x / (width / cols))


# ---- a camera straight on the service's bus: PNG and JPEG, bare, with and without an encoding --------------


@pytest.mark.parametrize(
    ("form", "encoding"),
    [("png", None), ("png", "image/png"), ("jpeg", None), ("jpeg", "image/jpeg")],
    ids=["png-no-encoding", "png", "jpeg-no-encoding", "jpeg"],
)
def test_a_bare_camera_gets_maps_and_the_readme_probe_answers(tiny_backend, tmp_path: Path, form, encoding) -> None:  # type: ignore[no-untyped-def]
    image = textured_image(480, 640)
    data = encode_png(image) if form == "png" else encode_jpeg(image)
    with service_and_robot(tiny_backend, tmp_path) as setup:
        received = maps_of(setup.client, SOURCE)
        camera_bus = zenoh.open(connecting_config(setup.port))
        camera = Camera(camera_bus, f"gcdtrav/in/{SOURCE}", data, encoding, (640, 480)).start()
        try:
            assert wait_until(lambda: len(received) >= 1, 30), setup.client.status().rejected_by_reason
            assert received[0].header.image_size == (640, 480)
            probe = run_example(setup.port, "planner_probe.py", "--source", SOURCE, "--x", "320", "--y", "400")
            assert probe.returncode == 0, probe.stderr
            assert "T (mean)" in probe.stdout and "pixel (x=320, y=400)" in probe.stdout
            status = setup.client.status()
            assert status.rejected_by_reason == {} and status.sources[SOURCE].rejected == 0
        finally:
            camera.stop()
            camera_bus.close()


@pytest.mark.parametrize("suffix", [".png", ".jpg"])
def test_the_readme_robot_and_planner_examples_on_a_folder(tiny_backend, tmp_path: Path, suffix: str) -> None:  # type: ignore[no-untyped-def]
    """The README's `robot_stream_folder.py my_images/ --source r1/front --fps 2`, then
    `planner_probe.py --source r1/front --x 320 --y 400` and `gcdtrav probe r1/front 320 400`, as written."""
    import cv2

    folder = tmp_path / "my_images"
    folder.mkdir()
    for index in range(2):
        cv2.imwrite(str(folder / f"{index:03d}{suffix}"), textured_image(480, 640, seed=index))
    with service_and_robot(tiny_backend, tmp_path) as setup:
        robot = run_example(setup.port, "robot_stream_folder.py", str(folder), "--source", SOURCE, "--fps", "2")
        assert robot.returncode == 0, robot.stderr
        assert f"maps {SOURCE} seq=" in robot.stdout
        planner = run_example(setup.port, "planner_probe.py", "--source", SOURCE, "--x", "320", "--y", "400")
        assert planner.returncode == 0 and "pixel (x=320, y=400) in seq=" in planner.stdout, planner.stderr
        probe = gcdtrav(setup.port, "probe", SOURCE, "320", "400")
        assert probe.returncode == 0 and "patch (row i=80, column j=48)" in probe.stdout, probe.stderr


# ---- a relayed camera: answers in the camera's pixels ------------------------------------------------------


def test_a_relayed_camera_is_answered_in_its_own_pixels(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    """The README's `--x 320 --y 400` on a 1920x1200 camera relayed at 563x352: the maps and answers are in
    the camera's pixels, and the pixel points at the patch it covers."""
    image = textured_image(1200, 1920)
    with service_and_robot(tiny_backend, tmp_path, relay={"max_side": 563}) as setup:
        received = maps_of(setup.client, SOURCE)
        camera = Camera(setup.bus, CAMERA_KEY, encode_jpeg(image), "image/jpeg", (1920, 1200)).start()
        try:
            assert wait_until(lambda: len(received) >= 1, 60), "no maps of the relayed camera"
            # Stopped before the queries by seq: only the frames in flight follow (the relay's slot, the service's
            # queue), so the service's history (8 frames a source) still holds the one queried, however slowly
            # the queries go on a loaded machine.
            camera.stop()
            header = received[-1].header
            assert header.image_size == (1920, 1200)  # the camera's, not the 563x352 frame's
            assert header.map_shape == (TINY_INPUT_SIZE, TINY_INPUT_SIZE)
            assert header.scale == (1920 / TINY_INPUT_SIZE, 1200 / TINY_INPUT_SIZE)

            answer = setup.client.patch(SOURCE, x=320, y=400, seq=header.seq)
            i, j = expected_patch(320, 400, (1920, 1200), header.map_shape)
            assert answer.patch == (i, j) == (32, 16)
            same = setup.client.patch_by_index(SOURCE, i, j, seq=header.seq)
            assert np.allclose(answer.weights, same.weights)
            corner = setup.client.patch(SOURCE, x=1919, y=1199, seq=header.seq)
            assert corner.patch == (TINY_INPUT_SIZE - 1, TINY_INPUT_SIZE - 1)
            region = setup.client.region(SOURCE, 0, 0, 1920, 1200, seq=header.seq)
            assert region.region == (0, 0, TINY_INPUT_SIZE, TINY_INPUT_SIZE)

            probe = run_example(setup.port, "planner_probe.py", "--source", SOURCE, "--x", "320", "--y", "400")
            assert probe.returncode == 0, probe.stderr
            far = gcdtrav(setup.port, "probe", SOURCE, "1920", "10")
            assert far.returncode == 1 and "outside the 1920x1200 image" in far.stderr
        finally:
            camera.stop()


def test_a_relayed_png_camera_gets_maps(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    """A camera key of bare PNGs without an encoding: the relay took them for envelopes and never sent one."""
    with service_and_robot(tiny_backend, tmp_path, relay={}) as setup:
        received = maps_of(setup.client, SOURCE)
        camera = Camera(setup.bus, CAMERA_KEY, encode_png(textured_image(240, 320)), None, (320, 240)).start()
        try:
            assert wait_until(lambda: len(received) >= 1, 60), "no maps of the relayed PNG camera"
            assert setup.relay is not None and setup.relay.camera(SOURCE).undecodable == 0
            assert received[-1].header.image_size == (320, 240)
        finally:
            camera.stop()


# ---- a starved source is visible, and the robot side hears why ---------------------------------------------


def test_a_camera_whose_every_frame_is_stale_is_shown_with_why_on_both_sides(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    """A robot clock an hour behind on a fleet that promised synchronised clocks (``clock: synced``; the default
    learns the robot's clock and serves it): every frame is stale by the service's clock. The status lists the
    source with its drops by reason and the detail; the relay's health, its staleness log and watch_freshness
    (on either bus) name the reason the service gave."""
    with service_and_robot(tiny_backend, tmp_path, relay={}, max_frame_age_s=2.0, clock="synced") as setup:
        camera = Camera(setup.bus, CAMERA_KEY, encode_jpeg(textured_image(240, 320)), None, (320, 240))
        camera.envelope, camera.age_s = PixelEncoding.JPEG, 3600.0
        service_side: list[Staleness] = []
        robot_client = TraversabilityClient(session=setup.bus)
        robot_side: list[Staleness] = []
        watches = [
            setup.client.watch_freshness([SOURCE], 1.0, service_side.append, period_s=0.1),
            robot_client.watch_freshness([SOURCE], 1.0, robot_side.append, period_s=0.1),
        ]
        health: list[RelayHealth] = []
        listener = setup.bus.declare_subscriber(
            f"gcdtrav/relay/{SOURCE}/health", lambda s: health.append(RelayHealth.unpack(s.payload.to_bytes()))
        )
        camera.start()
        try:
            assert wait_until(lambda: getattr(setup.client.status().sources.get(SOURCE), "stale", 0) >= 3, 30)
            source = setup.client.status().sources[SOURCE]
            assert source.refused and source.processed == 0  # refused before it took a slot, yet listed
            assert source.dropped_by_reason == {"stale": source.dropped} and source.received == source.dropped
            assert source.problem.startswith("stale: captured 3600.") and "max_frame_age_s = 2 s" in source.problem

            table = gcdtrav(setup.port, "status")
            assert table.returncode == 0, table.stderr
            row = next(line for line in table.stdout.splitlines() if line.startswith(SOURCE))
            assert "stale" in row and "refused" in row
            assert f"{SOURCE} (box-1): stale: captured 3600." in table.stdout

            assert wait_until(lambda: bool(health) and (health[-1].problem or "").startswith("stale: captured"), 30)
            for changes in (setup.changes, service_side, robot_side):  # the relay's, watch_freshness on both buses
                assert wait_until(lambda seen=changes: any(said_stale(c) for c in seen), 30)
            assert "stale: captured" in (watches[0].reason(SOURCE) or "")
        finally:
            camera.stop()
            listener.undeclare()
            for watch in watches:
                watch.close()
            robot_client.close()


def said_stale(change: Staleness) -> bool:
    return change.stale and (change.reason or "").startswith("stale: captured 3600.")


# ---- the README's Python snippet ---------------------------------------------------------------------------


def readme_snippet(port: int) -> str:
    """The README's client example, as written, but on loopback without multicast scouting."""
    text = (REPO / "README.md").read_text("utf-8")
    start = text.index("```python\nimport queue")
    code = text[start + len("```python\n") : text.index("```", start + 10)]
    assert 'zenoh_config(mode="peer")' in code
    return code.replace('zenoh_config(mode="peer")', f"connecting_config({port})")


@pytest.mark.parametrize("start_with_puddle", [False, True], ids=["paper-set", "set-with-puddle"])
def test_the_readme_python_snippet_runs(tiny_backend, tmp_path: Path, start_with_puddle: bool) -> None:  # type: ignore[no-untyped-def]
    """It added "puddle" to the active set, which failed (duplicate concept) once the active set held one, as
    after the README's own `gcdtrav anchors set examples/anchors/puddles.yaml`."""
    from gcdtrav.schemas.anchors import AnchorSet, default_anchor_set

    start = AnchorSet.load(REPO / "examples" / "anchors" / "puddles.yaml") if start_with_puddle else None
    settings = ServiceSettings(state_dir=tmp_path, instance="box-1", preview=False)
    with in_process_service(tiny_backend, settings, start) as (service, port):
        before = service.pipeline.anchors.version
        namespace = {"connecting_config": connecting_config}
        errors: list[BaseException] = []

        def run() -> None:
            try:
                exec(compile(readme_snippet(port), "README.md", "exec"), namespace)  # the README's code, as written
            except BaseException as err:
                errors.append(err)

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        thread.join(60)
        assert not thread.is_alive(), "the snippet hung"
        assert errors == []
        assert service.pipeline.anchors.version == before  # swapped in, then rolled back
        assert (before != default_anchor_set().version) == start_with_puddle  # the service started as asked
