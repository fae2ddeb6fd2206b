"""A second instance with another checkpoint on the same prefix takes no robot and says why; with
allow_mixed_models it shares them. Two instances in this process on a router of the test's own."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import pytest
import zenoh
from conftest import build_tiny_clipseg, textured_image
from zenoh_helpers import client_config, free_port, start_router, subscribed_elsewhere, wait_until

pytest.importorskip("torch")

from gcdtrav.client import TraversabilityClient
from gcdtrav.client.commands.operator import print_status
from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.schemas.config import EngineSettings
from gcdtrav.schemas.keys import input_key
from gcdtrav.schemas.settings import ServiceSettings, SettingsError
from gcdtrav.service.backends.clipseg import ClipSegBackend
from gcdtrav.service.bus.node import TraversabilityService
from gcdtrav.service.pipeline import Pipeline

IMAGE = textured_image(48, 64)
SOURCES = [f"r{i}/front" for i in range(4)]


def start(backend: Any, port: int, instance: str, state_dir: Path, **extra: Any) -> TraversabilityService:
    session = zenoh.open(client_config(port))
    settings = ServiceSettings(state_dir=state_dir, instance=instance, preview=False, **extra)
    service = TraversabilityService(session, Pipeline(backend, default_anchor_set(), EngineSettings()), settings)
    service.start()
    return service


def stop(service: TraversabilityService) -> None:
    service.stop()
    service.session.close()


def owners(service: TraversabilityService) -> dict[str, str | None]:
    assert service.membership is not None
    return {source: service.membership.owner(source) for source in SOURCES}


def test_another_checkpoint_takes_no_robot_says_why_and_shares_them_when_mixed_models_are_allowed(
    tiny_backend: Any, tmp_path: Path, caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str]
) -> None:
    other = ClipSegBackend(str(build_tiny_clipseg(tmp_path / "other", seed=1)))
    assert other.describe().fingerprint not in ("", tiny_backend.describe().fingerprint)
    port = free_port()
    router = start_router(port)
    caplog.set_level(logging.WARNING, logger="gcdtrav.service")
    a = start(tiny_backend, port, "box-a", tmp_path / "a")
    client = TraversabilityClient(config=client_config(port), timeout=3.0)
    try:
        with pytest.raises(SettingsError, match="in use by instance box-a"):  # never one state file for two
            start(other, port, "box-b", tmp_path / "a")
        b = start(other, port, "box-b", tmp_path / "b")
        assert wait_until(lambda: a.membership and a.membership.live() == {"box-a", "box-b"}, 60)
        # both answer through the router: it knows their input subscriptions (declared before, on the same link);
        # and the client knows of them: the images below are sent (they were sent at once before)
        assert wait_until(lambda: len(client.statuses(timeout=1.0)) == 2, 60)
        assert subscribed_elsewhere(client.session, input_key(client.input_prefix, SOURCES[0])), "the inputs"
        for _ in range(3):  # established sources: the bounded-load table, not only the highest weight
            for source in SOURCES:
                client.publish_image(source, IMAGE)
        assert wait_until(lambda: set(owners(a).values()) == {"box-a"} == set(owners(b).values()), 60), owners(b)
        why = b.status().model_refused
        assert "differs from the fleet's" in why and "allow_mixed_models" in why and not a.status().model_refused
        assert any("box-b joined (model" in r.getMessage() for r in caplog.records)
        assert any("this instance takes no sources" in r.getMessage() for r in caplog.records)
        assert wait_until(lambda: len(client.statuses(timeout=1.0)) == 2, 60)
        assert print_status(client) == 0
        table = capsys.readouterr().out
        assert "TAKES NO SOURCES box-b: model" in table and "MODELS DIFFER" in table, table

        stop(b)
        assert wait_until(lambda: a.membership and a.membership.live() == {"box-a"}, 60)
        assert any("box-b left" in r.getMessage() for r in caplog.records)
        b = start(other, port, "box-b", tmp_path / "b", allow_mixed_models=True)
        assert wait_until(lambda: len(client.statuses(timeout=1.0)) == 2, 60)  # the router routes to box-b again
        for source in SOURCES:
            client.publish_image(source, IMAGE)
        shared = lambda: set(owners(a).values()) == {"box-a", "box-b"} and owners(a) == owners(b)  # noqa: E731
        assert wait_until(shared, 60), (owners(a), owners(b))
        assert b.status().model_refused == ""
        stop(b)
    finally:
        client.close()
        stop(a)
        router.kill()
        router.communicate(timeout=10)


def test_two_instances_of_different_models_started_at_once_agree_on_the_one_that_serves(
    tiny_backend: Any, tmp_path: Path
) -> None:
    import threading

    other = ClipSegBackend(str(build_tiny_clipseg(tmp_path / "other", seed=2)))
    port = free_port()
    router = start_router(port)
    started: dict[str, TraversabilityService] = {}
    threads = [
        threading.Thread(target=lambda n=name, b=backend: started.update({n: start(b, port, n, tmp_path / n)}))
        for name, backend in (("box-a", tiny_backend), ("box-b", other))
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60)
    a, b = started["box-a"], started["box-b"]
    client = TraversabilityClient(config=client_config(port), timeout=3.0)
    try:
        assert wait_until(lambda: a.membership and b.membership and len(b.membership.live()) == 2, 60)
        assert wait_until(lambda: len(client.statuses(timeout=1.0)) == 2, 60)  # the router knows both's inputs
        assert subscribed_elsewhere(client.session, input_key(client.input_prefix, SOURCES[0])), "the inputs"
        for _ in range(3):
            for source in SOURCES:
                client.publish_image(source, IMAGE)
        one_serves = lambda: len(set(owners(a).values())) == 1 and owners(a) == owners(b)  # noqa: E731
        assert wait_until(one_serves, 60), (owners(a), owners(b))
        serving = next(iter(set(owners(a).values())))
        refused = [s.instance for s in (a.status(), b.status()) if s.model_refused]
        assert refused == [name for name in ("box-a", "box-b") if name != serving]
    finally:
        client.close()
        for service in (a, b):
            stop(service)
        router.kill()
        router.communicate(timeout=10)
