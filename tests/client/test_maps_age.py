"""`Maps.age_s` for a robot whose clock is an hour off: the service judges the frame by its delay, and so does
the age the client reports (it said 3600 s for a map a second old)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from conftest import textured_image
from zenoh_helpers import connecting_config, service_reachable, subscribed_elsewhere, wait_until

pytest.importorskip("torch")

from gcdtrav.client import Maps, TraversabilityClient
from gcdtrav.schemas.settings import ServiceSettings

from tools.loopback import in_process_service


def test_maps_of_a_robot_with_a_wrong_clock_are_as_old_as_they_are(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    settings = ServiceSettings(state_dir=tmp_path, instance="box-1", preview=False)
    with (
        in_process_service(tiny_backend, settings) as (service, port),
        TraversabilityClient(config=connecting_config(port), timeout=5.0) as client,
    ):
        assert wait_until(lambda: service_reachable(client), 30)
        assert subscribed_elsewhere(client.session, "gcdtrav/in/r1/front"), "the service's input subscription"
        received: list[tuple[Maps, float]] = []  # the maps, and time.time() when they came
        subscriber = client.subscribe_maps("r1/front", lambda maps: received.append((maps, time.time())))
        assert subscribed_elsewhere(service.session, "gcdtrav/out/r1/front/maps"), "the client's maps subscription"
        for k in range(3):  # the robot's clock: an hour behind this one; a frame once the last one's maps came
            sent_at = time.time()
            client.publish_image("r1/front", textured_image(48, 64, seed=k), stamp=sent_at - 3600.0)
            assert wait_until(lambda n=k + 1: len(received) >= n, 30), f"no maps of frame {k}"
        subscriber.undeclare()
    maps, arrived = received[-1]
    # As old as they are: at receipt, no older than the frame's way from this publish to its maps' arrival here
    # (the service judges by the smallest delay of the robot's frames); now, no older than since the publish.
    assert maps.header.age_at_receipt_s is not None and maps.header.age_at_receipt_s <= arrived - sent_at
    age = maps.age_s
    assert 0.0 <= age <= time.time() - sent_at, age  # not 3600
    assert time.time() - maps.header.stamp > 3599  # the stamp stays the robot's
    legacy = Maps(maps.header.model_copy(update={"age_at_receipt_s": None}), maps.traversability, maps.uncertainty)
    assert legacy.age_s > 3599  # an older service's maps: now minus the stamp, as documented
