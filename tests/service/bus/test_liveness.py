"""A hung instance (inference stuck, process alive) leaves the fleet and comes back: liveness by progress.

Two instances in this process on a router of the test's own; one backend can be made to hang on demand.
"""

from __future__ import annotations

import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import pytest
import zenoh
from conftest import textured_image
from zenoh_helpers import (
    client_config,
    free_port,
    start_router,
    subscribed_elsewhere,
    wait_until,
)

pytest.importorskip("torch")

from gcdtrav.client import Maps, TraversabilityClient
from gcdtrav.client.commands.health import main as health_main
from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.schemas.config import EngineSettings
from gcdtrav.schemas.keys import input_key
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.bus.node import TraversabilityService
from gcdtrav.service.pipeline import Pipeline

IMAGE = textured_image(48, 64)
SOURCES = [f"r{i}/front" for i in range(4)]


class HangingBackend:
    """The real backend, except that while ``hang`` is set each frame waits for ``release``."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self.hang = threading.Event()
        self.release = threading.Event()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def logits(self, image: Any, prepared: Any) -> Any:
        if self.hang.is_set():
            self.release.wait(60)
        return self.inner.logits(image, prepared)


def start(backend: Any, port: int, instance: str, state_dir: Path) -> tuple[TraversabilityService, zenoh.Session]:
    session = zenoh.open(client_config(port))
    settings = ServiceSettings(
        state_dir=state_dir, instance=instance, preview=False, stall_after_s=1.0, max_frame_age_s=1.5
    )
    service = TraversabilityService(session, Pipeline(backend, default_anchor_set(), EngineSettings()), settings)
    service.start()
    return service, session


def health(port: int, instance: str) -> int:
    flags = ["-m", "client", "-e", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"]
    return health_main([*flags, "--instance", instance, "--timeout", "10"])


def test_a_hung_instance_withdraws_reports_unhealthy_and_rejoins_when_it_progresses(
    tiny_backend: Any, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    port = free_port()
    router = start_router(port)
    hanging = HangingBackend(tiny_backend)
    a, session_a = start(hanging, port, "box-a", tmp_path / "a")
    b, session_b = start(tiny_backend, port, "box-b", tmp_path / "b")
    client = TraversabilityClient(config=client_config(port), timeout=3.0)
    by_source: dict[str, list[Maps]] = defaultdict(list)
    subscriber = client.subscribe_maps("**", lambda m: by_source[m.header.source].append(m))

    def publish_all(times: int = 1) -> None:
        for _ in range(times):
            for source in SOURCES:
                client.publish_image(source, IMAGE)
            time.sleep(0.2)

    try:
        for service in (a, b):
            assert wait_until(lambda s=service: s.membership.live() == {"box-a", "box-b"}, 60)  # type: ignore[misc]
        # the services' input subscriptions known to the client, its maps subscription to both services
        for source in SOURCES:
            assert subscribed_elsewhere(client.session, input_key(client.input_prefix, source)), source
        for service in (a, b):
            assert subscribed_elsewhere(service.session, service.keys.maps(SOURCES[0])), service.settings.instance
        publish_all(3)
        assert wait_until(lambda: all(by_source[s] for s in SOURCES), 60)
        owners = {source: a.membership.owner(source) for source in SOURCES}  # type: ignore[union-attr]
        assert owners == {source: b.membership.owner(source) for source in SOURCES}  # type: ignore[union-attr]
        assert sorted(owners.values()) == ["box-a", "box-a", "box-b", "box-b"]  # bounded loads: 2/2
        assert health(port, "box-a") == 0

        hanging.hang.set()
        a_sources = [s for s in SOURCES if owners[s] == "box-a"]
        hung_at = time.monotonic()
        for source in a_sources:
            by_source[source].clear()
        while time.monotonic() - hung_at < 60 and not all(
            any(m.header.instance == "box-b" for m in by_source[s]) for s in a_sources
        ):
            publish_all()
        assert all(any(m.header.instance == "box-b" for m in by_source[s]) for s in a_sources), "failed over"
        assert b.membership.live() == {"box-b"}  # type: ignore[union-attr]
        status = next(s for s in client.statuses() if s.instance == "box-a")
        assert status.healthy is False and "stalled: no progress" in status.reason
        capsys.readouterr()
        assert health(port, "box-a") == 1
        assert "unhealthy: instance box-a stalled: no progress" in capsys.readouterr().err
        assert health(port, "box-b") == 0

        hanging.hang.clear()
        hanging.release.set()  # the stuck frame finishes, long after max_frame_age_s: dropped, never published
        assert wait_until(lambda: b.membership.live() == {"box-a", "box-b"}, 60)  # type: ignore[union-attr]
        assert wait_until(lambda: a.status().healthy is True, 30)
        assert {"stale", "not_owner"} & set(a.status().dropped_by_reason)  # the stuck frame, counted
        publish_all(5)
        for maps in (m for source in SOURCES for m in by_source[source]):
            assert maps.header.published_at - maps.header.received_at <= 1.5
        assert health(port, "box-a") == 0
    finally:
        hanging.release.set()
        subscriber.undeclare()
        client.close()
        for service, session in ((a, session_a), (b, session_b)):
            service.stop()
            session.close()
        router.terminate()
        router.communicate(timeout=20)
