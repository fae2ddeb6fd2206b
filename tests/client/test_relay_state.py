"""The relay's decisions without zenoh: credits and their timeout, clock offset, rates, frame sizes, staleness."""

from __future__ import annotations

import math

import numpy as np
import pytest
from gcdtrav.client.freshness import FreshnessWatch
from gcdtrav.client.relay.state import (
    MAX_CREDIT_TIMEOUT_S,
    ClockEstimate,
    CreditWindow,
    RateWindow,
    downsized,
    target_size,
)
from gcdtrav.schemas.messages import CreditGrant


class Clock:
    def __init__(self, now: float = 1000.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


def grant(**kw: object) -> CreditGrant:
    fields = dict(source="cam", instance="box-1", grant=0, reason="taken", granted_at=0.0, model_input=(352, 352))
    return CreditGrant.model_validate(fields | {"max_frame_age_s": 5.0} | kw)


def test_the_first_frame_goes_then_each_waits_for_a_credit() -> None:
    clock = Clock()
    window = CreditWindow(timeout_s=2.0, clock=clock)
    assert window.ready()
    window.spend()
    assert not window.ready() and window.wait_s() == pytest.approx(2.0)
    clock.now += 0.5
    window.grant(grant())
    assert window.ready() and window.owner == "box-1" and window.timeouts == 0


def test_a_lost_credit_costs_one_timeout() -> None:
    clock = Clock()
    window = CreditWindow(timeout_s=2.0, clock=clock)
    window.spend()
    clock.now += 1.999
    assert not window.ready()
    clock.now += 0.001
    assert window.ready()
    window.spend()  # without a credit: counted
    assert window.timeouts == 1 and not window.ready()


def test_a_slow_service_stretches_the_timeout_within_a_cap() -> None:
    clock = Clock()
    window = CreditWindow(timeout_s=1.0, clock=clock)
    for _ in range(5):  # credits come 4 s after each frame: a busy service, not a lost credit
        window.spend()
        clock.now += 4.0
        window.grant(grant())
    assert window.timeout_s == pytest.approx(12.0)
    for _ in range(20):
        window.spend()
        clock.now += 100.0
        window.grant(grant())
    assert window.timeout_s == MAX_CREDIT_TIMEOUT_S


def test_clock_offset_from_the_shortest_round_trip() -> None:
    estimate = ClockEstimate()
    assert estimate.best() is None
    # service clock = robot clock + 10 s; 0.1 s each way, 0.5 s at the service
    estimate.add(grant(frame_sent_at=100.0, frame_received_at=110.1, granted_at=110.6), arrived_at=100.7)
    # a round trip slowed on the way back (0.9 s): a worse sample
    estimate.add(grant(frame_sent_at=200.0, frame_received_at=210.1, granted_at=210.6), arrived_at=201.5)
    estimate.add(grant(frame_sent_at=None, granted_at=0.0), arrived_at=5.0)  # nothing to learn
    round_trip, offset = estimate.best()  # type: ignore[misc]
    assert round_trip == pytest.approx(0.2) and offset == pytest.approx(10.0)


def test_rate_window_forgets_old_bytes() -> None:
    clock = Clock()
    rate = RateWindow(window_s=10.0, clock=clock)
    rate.add(50_000)
    clock.now += 5
    rate.add(50_000)
    assert rate.per_s() == pytest.approx(10_000)
    clock.now += 6
    assert rate.per_s() == pytest.approx(5_000) and rate.total == 100_000


@pytest.mark.parametrize(
    ("size", "max_side", "expected"),
    [
        ((1920, 1200), "auto", (563, 352)),  # the shorter side at the model's input
        ((1200, 1920), "auto", (352, 563)),
        ((640, 480), "auto", (469, 352)),
        ((320, 240), "auto", (320, 240)),  # never enlarged
        ((352, 352), "auto", (352, 352)),
        ((1920, 1200), 640, (640, 400)),  # the longer side at most N
        ((1920, 1200), 4000, (1920, 1200)),
        ((10000, 1), 16, (16, 1)),  # never below one pixel
    ],
)
def test_target_size_keeps_the_aspect(size: tuple[int, int], max_side: int | str, expected: tuple[int, int]) -> None:
    assert target_size(*size, max_side, (352, 352)) == expected


def test_downsized_frames_keep_their_content() -> None:
    image = np.zeros((1200, 1920, 3), np.uint8)
    image[:, 960:] = 200  # right half bright
    small = downsized(image, "auto", (352, 352))
    assert small.shape == (352, 563, 3) and small[:, :270].max() == 0 and small[:, 300:].min() == 200
    assert downsized(image[:100, :100], "auto", (352, 352)) is not None


def test_freshness_reports_stale_and_fresh_once_each() -> None:
    clock = Clock(100.0)
    watch = FreshnessWatch(stale_after_s=2.0, clock=clock)
    watch.watch("cam")  # from now: stale 2 s later without maps
    assert watch.newest("cam") is None and watch.age_s("cam") == 0.0 and watch.check() == []
    clock.now += 2.5
    [change] = watch.check()
    assert change.stale and change.source == "cam" and change.age_s == pytest.approx(2.5)
    assert math.isinf(watch.age_s("never watched"))
    clock.now = 100.0
    watch.observe("cam", 99.0)
    [change] = watch.check()
    assert not change.stale and change.age_s == pytest.approx(1.0)
    assert watch.check() == []
    clock.now = 101.0  # exactly at the limit: fresh
    assert watch.check() == [] and not watch.is_stale("cam")
    clock.now = 101.5
    [change] = watch.check()
    assert change.stale and change.age_s == pytest.approx(2.5)
    watch.observe("cam", 50.0)  # an older map changes nothing
    watch.observe("cam", math.nan)
    assert watch.newest("cam") == 99.0
    with pytest.raises(ValueError, match="positive"):
        FreshnessWatch(0.0)
