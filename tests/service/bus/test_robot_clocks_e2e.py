"""Robots as they are in the field, end to end on loopback: clocks an hour off, one publisher flooding."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest
from conftest import textured_image
from zenoh_helpers import connecting_config, service_reachable, subscribed_elsewhere, wait_until

pytest.importorskip("torch")

from gcdtrav.client import Maps, TraversabilityClient
from gcdtrav.schemas.keys import input_key
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.bus.node import TraversabilityService

from tools.loopback import anchor_set_at_start, in_process_service

HOUR = 3600.0
FRAMES = 6


@dataclass
class Serving:
    service: TraversabilityService
    port: int
    client: TraversabilityClient
    received: list[Maps]


@contextmanager
def serving(backend, state_dir: Path, **settings_kw: object) -> Iterator[Serving]:  # type: ignore[no-untyped-def]
    settings = ServiceSettings(state_dir=state_dir, instance="clocks-1", preview=False, **settings_kw)  # type: ignore[arg-type]
    with in_process_service(backend, settings, anchor_set_at_start(settings)) as (service, port):
        client = TraversabilityClient(config=connecting_config(port), timeout=5.0)
        received: list[Maps] = []
        subscriber = client.subscribe_maps("**", received.append)
        try:
            assert wait_until(lambda: service_reachable(client), 60)
            assert subscribed_elsewhere(service.session, service.keys.maps("probe")), "the maps subscription"
            assert subscribed_elsewhere(client.session, input_key(client.input_prefix, "probe")), "the inputs"
            yield Serving(service, port, client, received)
        finally:
            subscriber.undeclare()
            client.close()


def stream(client: TraversabilityClient, offsets: dict[str, float]) -> None:
    """FRAMES frames per robot, stamped now by its clock, 5 rounds a second."""
    image = textured_image(64, 80)
    for _ in range(FRAMES):
        for source, offset in offsets.items():
            client.publish_image(source, image, stamp=time.time() + offset)
        time.sleep(0.2)


def maps_of(received: list[Maps], source: str) -> list[Maps]:
    return [m for m in received if m.header.source == source]


def all_judged(run: Serving, sources: list[str]) -> bool:
    """Whether each of ``sources`` had its FRAMES frames judged (none waiting or in flight) and some of its maps
    came. A loaded machine drops some frames (the latest-only queue keeps the newest) and some maps on the way
    (published with congestion control DROP): the maps count follows what the service and the link did."""
    status = run.client.status()
    for name in sources:
        s = status.sources.get(name)
        if s is None or s.received < FRAMES or s.processed + s.unchanged + s.dropped + s.rejected < s.received:
            return False
        if not maps_of(run.received, name):
            return False
    return True


def counts_of(run: Serving, sources: list[str]) -> dict[str, object]:
    """Each source's counts and the maps received, for a failure's message."""
    status = run.client.status()
    return {name: (status.sources.get(name), len(maps_of(run.received, name))) for name in sources}


def test_robots_an_hour_behind_and_ahead_get_maps_with_their_own_stamps(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    offsets = {"behind/front": -HOUR, "ahead/front": HOUR, "synced/front": 0.0}
    with serving(tiny_backend, tmp_path) as run:  # the defaults: clock estimated
        stream(run.client, offsets)
        received = run.received
        assert wait_until(lambda: all_judged(run, list(offsets)), 60), counts_of(run, list(offsets))
        status = run.client.status()
    for source, offset in offsets.items():
        counts = status.sources[source]
        # maps for each robot; a frame dropped only as replaced by its robot's newer one, never as stale
        assert counts.processed + counts.unchanged >= 1 and counts.stale == 0, (source, counts)
        assert counts.rejected == 0 and "stale" not in counts.dropped_by_reason, (source, counts)
        for maps in maps_of(received, source):  # stamped by the robot's clock
            assert abs(maps.header.stamp - offset - maps.header.received_at) < 5
        learnt = status.sources[source].clock_offset_s
        assert learnt is not None and abs(learnt + offset) < 1.0
    assert status.rejected_by_reason == {} and "stale" not in status.dropped_by_reason


def test_with_clock_synced_the_same_robots_get_nothing_as_the_issue_reported(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    offsets = {"behind/front": -HOUR, "ahead/front": HOUR, "synced/front": 0.0}
    with serving(tiny_backend, tmp_path, clock="synced") as run:
        stream(run.client, offsets)
        received = run.received

        def counted() -> bool:
            status = run.client.status()
            return (
                status.dropped_by_reason.get("stale", 0) >= FRAMES
                and status.rejected_by_reason.get("skewed_stamp", 0) >= FRAMES
            )

        assert wait_until(counted, 60)
        assert wait_until(lambda: all_judged(run, ["synced/front"]), 60), counts_of(run, ["synced/front"])
        synced = run.client.status().sources["synced/front"]
        assert synced.processed + synced.unchanged >= 1 and synced.stale == 0, synced
    assert not maps_of(received, "behind/front") and not maps_of(received, "ahead/front")


def test_a_flooding_publisher_is_rate_limited_while_another_publishers_frames_are_all_admitted(
    tiny_backend, tmp_path: Path
) -> None:  # type: ignore[no-untyped-def]
    with serving(tiny_backend, tmp_path, intake_rate_per_publisher=20.0, max_frame_age_s=None) as run:
        robot = TraversabilityClient(config=connecting_config(run.port), timeout=5.0)
        try:
            # the robot's new session knows the service's input subscription: none of its 10 frames is lost
            assert wait_until(lambda: service_reachable(robot), 60)
            assert subscribed_elsewhere(robot.session, input_key(robot.input_prefix, "robot/front")), "the inputs"
            image = textured_image(32, 32)
            began = time.monotonic()
            for k in range(300):  # one publisher: far beyond 20 a second plus its 1 s burst
                run.client.publish_image(f"flood/n{k}", image)
            for _ in range(10):
                robot.publish_image("robot/front", image)
                time.sleep(0.05)

            def robot_received() -> int:
                source = run.client.status().sources.get("robot/front")
                return 0 if source is None else source.received

            def flood_counted() -> int:
                """The flood's frames the intake has judged: refused (by any reason) or taken in as a source."""
                status = run.client.status()
                taken = sum(source.received for name, source in status.sources.items() if name.startswith("flood/"))
                return sum(status.rejected_by_reason.values()) + sum(status.dropped_by_reason.values()) + taken

            assert wait_until(lambda: robot_received() == 10, 60)
            # the robot's frames came on another session and may overtake the flood's: wait for all 300 to be judged
            assert wait_until(lambda: flood_counted() >= 300, 60), flood_counted()
            status = run.client.status()
            elapsed_s = time.monotonic() - began  # the flood's frames all reached the intake within it
        finally:
            robot.close()
    # all but its 1 s burst and what refilled while they arrived (20 a second: about 1 s here, longer under load)
    assert 300 - 20 - 20 * elapsed_s <= status.rejected_by_reason["rate_limited"] < 300, elapsed_s
