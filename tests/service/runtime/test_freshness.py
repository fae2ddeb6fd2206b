"""Stamps, age and ownership: what may still become maps, and every other frame counted by reason."""

from __future__ import annotations

import time
from dataclasses import replace

import pytest
from fakes import assembled, image, png_frame
from gcdtrav.schemas.images import encode_png
from gcdtrav.schemas.inputs import DecodedFrame, RejectedInput
from gcdtrav.schemas.messages import ImageEnvelope, PixelEncoding
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.runtime.frames import PendingFrame
from gcdtrav.service.runtime.intake.freshness import ClockMode, Dropped, FrameGate, Freshness, check_stamp

LOG = __import__("logging").getLogger("test")


@pytest.mark.parametrize("stamp", [float("nan"), float("inf"), float("-inf"), -1.0])
def test_a_stamp_that_is_not_a_time_is_rejected(stamp: float) -> None:
    with pytest.raises(RejectedInput) as err:
        check_stamp(stamp)
    assert err.value.reason == "bad_stamp"
    check_stamp(0.0)  # simulated time starts at 0


@pytest.mark.parametrize("clock", ["estimated", "synced"])
def test_a_stamp_ahead_beyond_the_skew_is_rejected_at_intake_and_none_accepts_any(clock: ClockMode) -> None:
    at_limit, limited, unlimited = (
        Freshness(None, 5.0, clock),
        Freshness(None, 5.0, clock),
        Freshness(None, None, clock),
    )
    for rule in (at_limit, limited, unlimited):
        assert rule.at_intake("r", 1000.0, 1000.0).refusal is None  # learns offset 0
    assert at_limit.at_intake("r", 1005.1, 1000.1).refusal is None  # at the limit
    refusal = limited.at_intake("r", 1005.2, 1000.1).refusal
    assert isinstance(refusal, RejectedInput) and refusal.reason == "skewed_stamp"
    assert "max_stamp_skew_s" in refusal.detail
    assert unlimited.at_intake("r", 1e12, 1000.2).refusal is None


def test_gate_drops_frames_of_other_instances_and_frames_too_old() -> None:
    owned = {"mine"}
    now = [1000.0]
    gate = FrameGate(lambda source: source in owned, Freshness(5.0, None), clock=lambda: now[0])
    frame = replace(png_frame("mine"), received_at=1000.0)
    gate.before_publish(frame)
    now[0] = 1005.0
    gate.before_publish(frame)  # at the limit
    now[0] = 1005.1
    with pytest.raises(Dropped) as stale:
        gate.before_publish(frame)
    assert stale.value.reason == "stale" and "when its maps were ready" in stale.value.detail
    with pytest.raises(Dropped) as moved:
        gate.before_publish(replace(frame, source="theirs"))
    assert moved.value.reason == "not_owner"
    with pytest.raises(RejectedInput):
        gate.before_inference(frame, DecodedFrame(image(), float("nan"), ""))


def envelope_frame(source: str, stamp: float, received_at: float) -> PendingFrame:
    rgb = image()
    payload = ImageEnvelope(
        stamp=stamp, encoding=PixelEncoding.PNG, width=rgb.shape[1], height=rgb.shape[0], data=encode_png(rgb)
    ).pack()
    return PendingFrame(source, f"gcdtrav/in/{source}", payload, "application/msgpack", received_at)


def test_worker_counts_each_gated_frame_and_publishes_only_the_good_one() -> None:
    settings = ServiceSettings(
        max_frame_age_s=20.0, max_stamp_skew_s=600.0, reuse={"enabled": False}, schedule={"policy": "round_robin"}
    )  # 20 s: the good frame's age is this test's own time to process it (a loaded host may take seconds)
    runtime, sink, _ = assembled(settings, owns=lambda source: source != "moved")
    queue, stats, frames = runtime.queue, runtime.stats, runtime.worker
    now = time.time()
    queue.put("good", envelope_frame("good", now, now))
    queue.put("old", envelope_frame("old", now - 300, now - 300))  # e.g. queued before a SIGSTOP
    queue.put("slow", replace(envelope_frame("slow", now - 30, now), lag_s=25.0))  # judged at intake, waited
    queue.put("nan", envelope_frame("nan", float("nan"), now))
    queue.put("moved", envelope_frame("moved", now, now))
    frames.start()
    deadline = time.monotonic() + 60  # a failure's bound
    while sum(s.processed + s.dropped + s.rejected for s in stats.snapshot({}).sources.values()) < 5:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    assert frames.stop(time.monotonic() + 10)
    snapshot = stats.snapshot(queue.counters())
    assert [maps.header.source for maps in sink.maps()] == ["good"]
    assert snapshot.dropped_by_reason == {"stale": 2, "not_owner": 1}
    assert snapshot.rejected_by_reason == {"bad_stamp": 1}
    assert sink.maps()[0].header.stamp == now


@pytest.mark.parametrize("clock", ["estimated", "synced"])
def test_age_before_publishing_is_the_lag_at_intake_plus_the_wait_and_none_turns_it_off(clock: ClockMode) -> None:
    now = [1010.0]
    rule = Freshness(5.0, None, clock)
    gate = FrameGate(lambda source: True, rule, clock=lambda: now[0])
    received = replace(png_frame("mine"), received_at=1009.0)
    rule.at_intake("mine", 1008.9, 1008.0)  # its clock learnt: robot ahead by 0.9 s
    ahead = replace(received, lag_s=rule.at_intake("mine", 1009.5, 1009.0).lag_s)
    gate.before_publish(ahead)  # a robot clock slightly ahead: the receipt still ages it (1 s)
    buffered = replace(received, lag_s=rule.at_intake("mine", 1004.9, 1009.0).lag_s)
    with pytest.raises(Dropped):
        gate.before_publish(buffered)  # 4.5 s slower than the fastest (estimated) / 6 s by the clock (synced)
    now[0] = 1014.5
    with pytest.raises(Dropped):
        gate.before_publish(ahead)  # a clock ahead does not keep a frame young
    unlimited = FrameGate(lambda source: True, Freshness(None, None, clock), clock=lambda: now[0])
    unlimited.before_publish(replace(received, lag_s=1e9))
