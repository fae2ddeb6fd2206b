"""A source the service forgets (idle for source_idle_s) leaves the metrics: every series that named it is
gone from the next scrape, while a source still streaming keeps its own."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from conftest import textured_image
from zenoh_helpers import connecting_config, service_reachable, subscribed_elsewhere, wait_until

pytest.importorskip("torch")

from gcdtrav.client import TraversabilityClient
from gcdtrav.schemas.keys import input_key
from gcdtrav.schemas.settings import ServiceSettings
from prometheus_client import generate_latest

from tools.loopback import anchor_set_at_start, in_process_service


def series_of(registry: object, source: str) -> list[str]:
    text = generate_latest(registry).decode()  # type: ignore[arg-type]
    return [line for line in text.splitlines() if f'source="{source}"' in line]


def test_a_forgotten_source_leaves_the_metrics(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    settings = ServiceSettings(state_dir=tmp_path, instance="forgets", source_idle_s=2.0, preview=False)
    with (
        in_process_service(tiny_backend, settings, anchor_set_at_start(settings)) as (service, port),
        TraversabilityClient(config=connecting_config(port), timeout=5.0) as client,
    ):
        registry = service.metrics.registry
        assert wait_until(lambda: service_reachable(client), 60)
        # the service's input subscription known to the client: its one frame of gone/cam is sent
        assert subscribed_elsewhere(client.session, input_key(client.input_prefix, "gone/cam")), "the inputs"
        image = textured_image(48, 64)
        client.publish_image("gone/cam", image, stamp=time.time())
        assert wait_until(
            lambda: any("gcdtrav_map_age_seconds_count" in s for s in series_of(registry, "gone/cam")), 60
        )
        assert any("gcdtrav_clock_offset_seconds" in s for s in series_of(registry, "gone/cam"))
        began = time.monotonic()
        while time.monotonic() - began < 30 and series_of(registry, "gone/cam"):  # the bound of a failure only
            client.publish_image("stays/cam", image, stamp=time.time())  # the worker sweeps idle sources
            time.sleep(0.25)
        assert series_of(registry, "gone/cam") == []
        assert "gone/cam" not in client.status().sources
        staying = series_of(registry, "stays/cam")
        assert any("gcdtrav_frames_received_total" in s for s in staying)
        assert any("gcdtrav_map_age_seconds_count" in s for s in staying)
