"""The intake as the bus drives it, with robots' clocks as they are in the field (an hour off, ROS header
stamps, bare images) and one publisher flooding: what is queued, what is refused and how it is counted."""

from __future__ import annotations

import time
from collections.abc import Callable

import pytest
from fakes import Clock, assembled, image
from gcdtrav.schemas.images import encode_jpeg, encode_png
from gcdtrav.schemas.messages import ImageEnvelope, PixelEncoding
from gcdtrav.schemas.messages.credits import REFUSED, STALE
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.ros.cdr import RosTopic
from gcdtrav.service.runtime.intake.intake_rate import MAX_PUBLISHERS, IntakeRate

from tools.ros_fixtures import compressed_image_cdr

HOUR = 3600.0
RGB = image(16, 16)
COMPRESSED = RosTopic("/cam/image/compressed", "sensor_msgs/msg/CompressedImage", "rmw_zenoh")


class Service:
    """The runtime as the service assembles it, its worker driven one frame at a time (no threads; no glance:
    every frame goes straight to inference)."""

    def __init__(self, tracker_clock: Callable[[], float] = time.monotonic, **settings: object) -> None:
        settings = {"reuse": {"enabled": False}, "schedule": {"policy": "round_robin"}} | settings
        self.settings = ServiceSettings(**settings)  # type: ignore[arg-type]
        runtime, self.sink, self.credits = assembled(self.settings, clock=tracker_clock)
        self.queue, self.stats, self.freshness = runtime.queue, runtime.stats, runtime.freshness
        self.sources, self.admission, self.worker = runtime.sources, runtime.admission, runtime.worker

    @property
    def freed(self) -> list[tuple[str, str]]:
        return [(grant.source, grant.reason) for grant in self.credits.grants]

    @property
    def published(self) -> list[tuple[str, float]]:
        return [(maps.header.source, maps.header.stamp) for maps in self.sink.maps()]

    def envelope(self, source: str, stamp: float) -> bool:
        payload = ImageEnvelope(
            stamp=stamp, encoding=PixelEncoding.PNG, width=16, height=16, data=encode_png(RGB)
        ).pack()
        return self.offer(source, payload, "application/msgpack")

    def ros(self, source: str, stamp: float) -> bool:
        return self.offer(source, compressed_image_cdr(encode_jpeg(RGB, 90), stamp), "", COMPRESSED)

    def offer(self, source: str, payload: bytes, encoding: str, ros: RosTopic | None = None) -> bool:
        read = lambda: payload  # noqa: E731
        return self.admission.offer(source, f"gcdtrav/in/{source}", len(payload), read, encoding, ros)

    def serve(self) -> None:
        while (item := self.queue.take(0)) is not None:
            _, pending = item
            inferred = self.worker._guarded(pending, self.worker._infer, pending)
            if inferred is not None:
                self.worker._guarded(pending, self.worker._finish, inferred)

    def stream(self, send: str, source: str, offset: float, frames: int = 5) -> None:
        """``frames`` frames stamped now by a clock ``offset`` off, each served before the next."""
        for _ in range(frames):
            getattr(self, send)(source, time.time() + offset)
            self.serve()

    def status(self):  # type: ignore[no-untyped-def]
        return self.stats.snapshot(self.queue.counters(), self.freshness.offsets.offsets())


@pytest.mark.parametrize("send", ["envelope", "ros"])
@pytest.mark.parametrize("offset", [-HOUR, HOUR, 0.0])
def test_a_robot_with_its_clock_off_by_an_hour_gets_its_maps_with_its_own_stamps(send: str, offset: float) -> None:
    service = Service()
    service.stream(send, "r1/front", offset)
    status = service.status()
    assert len(service.published) == 5 and status.rejected_by_reason == {} and status.dropped_by_reason == {}
    assert all(abs(stamp - (time.time() + offset)) < 5 for _, stamp in service.published)  # the robot's clock
    learnt = status.sources["r1/front"].clock_offset_s
    assert learnt is not None and abs(learnt + offset) < 1.0


@pytest.mark.parametrize("send", ["envelope", "ros"])
def test_with_clock_synced_a_robot_an_hour_behind_is_dropped_stale_and_its_credit_says_so(send: str) -> None:
    service = Service(clock="synced")
    service.stream(send, "r1/front", -HOUR)
    status = service.status()
    assert not service.published and status.dropped_by_reason == {"stale": 5}
    assert service.freed == [("r1/front", STALE)] * 5
    refused = status.sources["r1/front"]  # never took a slot: listed as refused, with why
    assert refused.refused and refused.stale == 5 and "by the service's clock" in refused.problem


def test_with_clock_synced_a_robot_an_hour_ahead_is_rejected_skewed_and_its_slot_freed() -> None:
    service = Service(clock="synced")
    service.stream("envelope", "r1/front", HOUR)
    status = service.status()
    assert status.rejected_by_reason == {"skewed_stamp": 5} and not service.published
    assert status.sources["r1/front"].refused and "sync the robot's clock" in status.sources["r1/front"].problem
    assert service.freed == [("r1/front", REFUSED)] * 5


def test_with_clock_synced_a_tracked_source_whose_clock_steps_back_is_dropped_stale_from_then_on() -> None:
    service = Service(clock="synced")
    service.stream("envelope", "r1/front", 0.0, frames=2)
    service.stream("envelope", "r1/front", -HOUR, frames=2)
    status = service.status()
    assert status.dropped_by_reason == {"stale": 2} and len(service.published) == 2
    assert status.sources["r1/front"].stale == 2


def test_a_backlog_of_frames_ten_seconds_old_after_an_outage_is_dropped() -> None:
    service = Service()
    service.stream("envelope", "r1/front", -HOUR)
    backlog_from = time.time() - 10.0
    for k in range(10):  # what a link buffered, delivered at once, 10 s old down to 9.1 s
        service.envelope("r1/front", backlog_from + k * 0.1 - HOUR)
        service.serve()
    service.stream("envelope", "r1/front", -HOUR)
    status = service.status()
    assert status.dropped_by_reason == {"stale": 10} and len(service.published) == 10
    assert status.sources["r1/front"].clock_offset_s == pytest.approx(HOUR, abs=1.0)  # not taken for a step


def test_bare_images_are_served_and_learn_no_clock() -> None:
    service = Service()
    for _ in range(3):
        service.offer("cam", encode_jpeg(RGB, 90), "image/jpeg")
        service.serve()
    status = service.status()
    assert len(service.published) == 3 and status.sources["cam"].clock_offset_s is None
    assert all(abs(stamp - time.time()) < 5 for _, stamp in service.published)  # stamp = receipt


def test_a_replayed_bag_from_2023_is_served_with_no_age_limit() -> None:
    service = Service(max_frame_age_s=None)
    bag = 1_690_000_000.0 - time.time()
    service.stream("ros", "bag/cam", bag)
    assert len(service.published) == 5 and service.status().rejected_by_reason == {}


def test_an_idle_source_forgets_its_clock() -> None:
    clock = Clock()
    service = Service(tracker_clock=clock)
    service.stream("envelope", "r1/front", -HOUR, frames=2)
    assert "r1/front" in service.freshness.offsets.offsets()
    clock.now = 1000.0
    assert service.sources.sweep() == ["r1/front"] and "r1/front" not in service.freshness.offsets.offsets()


# ---- intake rate per publisher ---------------------------------------------------------------------


def test_a_flood_from_one_publisher_is_limited_while_another_is_admitted_in_full() -> None:
    clock = Clock()
    rate = IntakeRate(per_publisher=100.0, anonymous=1000.0, burst_s=1.0, clock=clock)
    flood = steady = 0
    for tick in range(10_000):  # 10 s: the flooder puts 1000 a second, the robot 15
        clock.now = tick / 1000
        flood += rate.admit("flooder")
        if tick % 67 == 0:
            steady += rate.admit("robot")
    assert steady == 150  # every one
    assert 100 + 100 * 9.9 <= flood <= 100 + 100 * 10 + 1  # the burst, then the rate


def test_samples_without_source_info_share_one_bucket_and_null_means_no_limit() -> None:
    clock = Clock()
    rate = IntakeRate(per_publisher=10.0, anonymous=50.0, clock=clock)
    assert sum(rate.admit(None) for _ in range(200)) == 50  # whoever sends them
    assert sum(rate.admit("p") for _ in range(200)) == 10 and len(rate) == 1
    clock.now = 1.0
    assert sum(rate.admit(None) for _ in range(200)) == 50
    free = IntakeRate(per_publisher=None, anonymous=None, clock=clock)
    assert all(free.admit(who) for who in [None, "p"] * 10_000) and len(free) == 0


def test_a_tiny_rate_still_admits_one_frame_and_refills() -> None:
    clock = Clock()
    rate = IntakeRate(per_publisher=0.5, anonymous=None, burst_s=1.0, clock=clock)
    assert rate.admit("slow") and not rate.admit("slow")
    clock.now = 2.0
    assert rate.admit("slow")


def test_publishers_are_bounded_full_buckets_first() -> None:
    clock = Clock()
    rate = IntakeRate(per_publisher=10.0, anonymous=None, clock=clock)
    for k in range(MAX_PUBLISHERS):
        rate.admit(f"p{k}")
    clock.now = 10.0  # every bucket full again
    assert rate.admit("busy") and len(rate) == 1
    for k in range(MAX_PUBLISHERS + 10):  # all active: the least recently used half goes
        rate.admit(f"q{k}")
    assert len(rate) <= MAX_PUBLISHERS
