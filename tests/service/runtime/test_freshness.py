"""Stamps, age and ownership: what may still become maps, and every other frame counted by reason."""

from __future__ import annotations

import time
from dataclasses import replace

import pytest
from fakes import image, pipeline, png_frame
from gcdtrav.schemas.images import encode_png
from gcdtrav.schemas.inputs import DecodedFrame, RejectedInput
from gcdtrav.schemas.messages import ImageEnvelope, PixelEncoding
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.runtime.frames import PendingFrame, ProcessedFrame
from gcdtrav.service.runtime.freshness import Dropped, FrameGate, check_stamp
from gcdtrav.service.runtime.history import FrameHistory
from gcdtrav.service.runtime.latest_queue import LatestFrameQueue
from gcdtrav.service.runtime.progress import ProgressMonitor
from gcdtrav.service.runtime.sources import SourceTracker
from gcdtrav.service.runtime.stats import ServiceStats
from gcdtrav.service.runtime.worker import FrameWorker

LOG = __import__("logging").getLogger("test")


@pytest.mark.parametrize("stamp", [float("nan"), float("inf"), float("-inf"), -1.0])
def test_a_stamp_that_is_not_a_time_is_rejected_whatever_the_skew_setting(stamp: float) -> None:
    for skew in (None, 1e9):
        with pytest.raises(RejectedInput) as err:
            check_stamp(stamp, 1000.0, skew)
        assert err.value.reason == "bad_stamp"


def test_a_stamp_ahead_of_its_receipt_beyond_the_skew_is_rejected_and_none_accepts_any() -> None:
    check_stamp(1000.0 + 5.0, 1000.0, 5.0)  # at the limit
    check_stamp(0.0, 1000.0, 5.0)  # the past is max_frame_age_s's to judge (simulated time starts at 0)
    with pytest.raises(RejectedInput) as err:
        check_stamp(1005.01, 1000.0, 5.0)
    assert err.value.reason == "skewed_stamp" and "max_stamp_skew_s" in err.value.detail
    check_stamp(1e12, 1000.0, None)


def test_gate_drops_frames_of_other_instances_and_frames_too_old() -> None:
    owned = {"mine"}
    now = [1000.0]
    gate = FrameGate(lambda source: source in owned, 5.0, None, clock=lambda: now[0])
    frame = replace(png_frame("mine"), received_at=1000.0)
    gate.before_publish(frame, 1000.0)
    now[0] = 1005.0
    gate.before_publish(frame, 1000.0)  # at the limit
    now[0] = 1005.1
    with pytest.raises(Dropped) as stale:
        gate.before_publish(frame, 1000.0)
    assert stale.value.reason == "stale"
    with pytest.raises(Dropped) as moved:
        gate.before_publish(replace(frame, source="theirs"), 1000.0)
    assert moved.value.reason == "not_owner"
    with pytest.raises(RejectedInput):
        gate.before_inference(frame, DecodedFrame(image(), float("nan"), ""))


class Outputs:
    def __init__(self) -> None:
        self.published: list[ProcessedFrame] = []

    def publish(self, done: ProcessedFrame) -> bool:
        self.published.append(done)
        return True


def envelope_frame(source: str, stamp: float, received_at: float) -> PendingFrame:
    rgb = image()
    payload = ImageEnvelope(
        stamp=stamp, encoding=PixelEncoding.PNG, width=rgb.shape[1], height=rgb.shape[0], data=encode_png(rgb)
    ).pack()
    return PendingFrame(source, f"gcdtrav/in/{source}", payload, "application/msgpack", received_at)


def test_worker_counts_each_gated_frame_and_publishes_only_the_good_one() -> None:
    queue: LatestFrameQueue[PendingFrame] = LatestFrameQueue()
    stats, outputs = ServiceStats(LOG), Outputs()
    settings = ServiceSettings(max_frame_age_s=2.0, max_stamp_skew_s=60.0)
    gate = FrameGate(lambda source: source != "moved", settings.max_frame_age_s, settings.max_stamp_skew_s)
    progress = ProgressMonitor(settings.stall_after_s)
    frames = FrameWorker(
        queue,
        pipeline(),
        FrameHistory(2),
        stats,
        SourceTracker(8, 60),
        settings,
        outputs.publish,
        progress=progress,
        gate=gate,
    )
    now = time.time()
    queue.put("good", envelope_frame("good", now, now))
    queue.put("old", envelope_frame("old", now - 30, now - 30))  # e.g. queued before a SIGSTOP
    queue.put("nan", envelope_frame("nan", float("nan"), now))
    queue.put("skewed", envelope_frame("skewed", now + 3600, now))
    queue.put("moved", envelope_frame("moved", now, now))
    frames.start()
    deadline = time.monotonic() + 10
    while sum(s.processed + s.dropped + s.rejected for s in stats.snapshot({}).sources.values()) < 5:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    assert frames.stop(time.monotonic() + 10)
    snapshot = stats.snapshot(queue.counters())
    assert [done.source for done in outputs.published] == ["good"]
    assert snapshot.dropped_by_reason == {"stale": 1, "not_owner": 1}
    assert snapshot.rejected_by_reason == {"bad_stamp": 1, "skewed_stamp": 1}
    assert outputs.published[0].image.stamp == now


def test_age_before_publishing_counts_from_the_older_of_stamp_and_receipt_and_none_turns_it_off() -> None:
    now = [1010.0]
    frame = replace(png_frame("mine"), received_at=1009.0)
    gate = FrameGate(lambda source: True, 5.0, None, clock=lambda: now[0])
    gate.before_publish(frame, 1009.5)  # a robot clock slightly ahead: the receipt ages it (1 s)
    with pytest.raises(Dropped):
        gate.before_publish(frame, 1004.0)  # captured 6 s ago, received 1 s ago (a link's buffer)
    now[0] = 1014.5
    with pytest.raises(Dropped):
        gate.before_publish(frame, 1100.0)  # a clock far ahead does not keep a frame young
    unlimited = FrameGate(lambda source: True, None, None, clock=lambda: now[0])
    unlimited.before_publish(frame, 0.0)
