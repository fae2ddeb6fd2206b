"""Unchanged views on the bus: a parked robot's repeated view is answered with its last maps (the client
sees ``reused``, ``computed_stamp``), a change and an anchor swap are inferred, and the status counts it all."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import textured_image
from zenoh_helpers import connecting_config, service_reachable, subscribed_elsewhere, wait_until

pytest.importorskip("torch")

from gcdtrav.client import Maps, TraversabilityClient
from gcdtrav.schemas.settings import ServiceSettings

from tools.loopback import anchor_set_at_start, in_process_service

TWO_ANCHORS = {
    "name": "puddles",
    "anchors": [{"concept": "puddle", "position": 0.0}, {"concept": "road", "position": 1.0, "width": 0.05}],
}


def scene(seed: int) -> np.ndarray:
    return textured_image(120, 160, seed=seed)


def with_person(image: np.ndarray) -> np.ndarray:
    out = image.copy()
    out[30:110, 60:90] = (20, 30, 220)
    return out


def test_a_repeated_view_is_answered_with_its_last_maps_and_changes_are_inferred(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    settings = ServiceSettings(state_dir=tmp_path, instance="reuse-1", max_frame_age_s=None, preview=False)
    with in_process_service(tiny_backend, settings, anchor_set_at_start(settings)) as (service, port):
        client = TraversabilityClient(config=connecting_config(port), timeout=5.0)
        received: list[Maps] = []
        subscriber = client.subscribe_maps("**", received.append)
        try:
            assert wait_until(lambda: service_reachable(client), 60)
            assert subscribed_elsewhere(service.session, service.keys.maps("parked")), "the maps subscription"

            def publish(image: np.ndarray, stamp: float) -> Maps:
                before = len(received)
                client.publish_image("parked", image, stamp=stamp, compression="jpeg")
                assert wait_until(lambda: len(received) > before, 60), "no maps"
                return received[-1]

            first = publish(scene(1), 1000.0)
            assert not first.reused and first.computed_stamp == 1000.0 and first.header.seq == 0
            again = publish(scene(1), 1000.2)
            assert again.reused and again.header.computed_from == (1000.0, 0) and again.computed_stamp == 1000.0
            assert again.header.stamp == 1000.2 and again.header.order[0] == 1000.2  # shown as the newest
            np.testing.assert_array_equal(again.traversability, first.traversability)
            assert client.patch("parked", 10, 10, seq=again.header.seq).seq == 0  # its seq answers queries

            changed = publish(with_person(scene(1)), 1000.4)
            assert not changed.reused and changed.header.seq == 1

            version = client.set_anchors(TWO_ANCHORS)
            swapped = publish(with_person(scene(1)), 1000.6)
            assert not swapped.reused and swapped.header.anchor_set_version == version  # never the old set's maps

            status = client.status().sources["parked"]
            assert (status.processed, status.unchanged) == (3, 1)
            assert status.received == status.processed + status.unchanged + status.dropped + status.rejected
            assert status.weight is not None and status.weight > 0 and status.share == pytest.approx(1.0)
        finally:
            subscriber.undeclare()
            client.close()
