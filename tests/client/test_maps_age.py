"""`Maps.age_s` for a robot whose clock is an hour off: the service judges the frame by its delay, and so does
the age the client reports (it said 3600 s for a map a second old)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from conftest import textured_image
from zenoh_helpers import connecting_config, service_reachable, wait_until

pytest.importorskip("torch")

from gcdtrav.client import Maps, TraversabilityClient
from gcdtrav.schemas.settings import ServiceSettings

from tools.loopback import in_process_service


def test_maps_of_a_robot_with_a_wrong_clock_are_as_old_as_they_are(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    settings = ServiceSettings(state_dir=tmp_path, instance="box-1", preview=False)
    with (
        in_process_service(tiny_backend, settings) as (_, port),
        TraversabilityClient(config=connecting_config(port), timeout=5.0) as client,
    ):
        assert wait_until(lambda: service_reachable(client), 10)
        received: list[Maps] = []
        subscriber = client.subscribe_maps("r1/front", received.append)
        time.sleep(0.3)
        for k in range(3):  # the robot's clock: an hour behind this one
            client.publish_image("r1/front", textured_image(48, 64, seed=k), stamp=time.time() - 3600.0)
            time.sleep(0.2)
        assert wait_until(lambda: len(received) >= 2, 20), "no maps"
        subscriber.undeclare()
    maps = received[-1]
    assert maps.header.age_at_receipt_s is not None and maps.header.age_at_receipt_s < 1.0
    assert 0.0 <= maps.age_s < 5.0, maps.age_s  # not 3600
    assert time.time() - maps.header.stamp > 3599  # the stamp stays the robot's
    legacy = Maps(maps.header.model_copy(update={"age_at_receipt_s": None}), maps.traversability, maps.uncertainty)
    assert legacy.age_s > 3599  # an older service's maps: now minus the stamp, as documented
