"""The service's side of slow links without a bus: stale frames dropped at intake and before inference,
credits at every freed slot, the compact maps."""

from __future__ import annotations

import time

import numpy as np
import pytest
from fakes import MAP_SIDE, assembled, processed
from gcdtrav.client.client import Maps
from gcdtrav.schemas.images import encode_jpeg
from gcdtrav.schemas.messages import ImageEnvelope, PixelEncoding
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.runtime.frames import FrameTimes, PendingFrame
from gcdtrav.service.runtime.intake.admission import Admission
from gcdtrav.service.runtime.intake.sources import SourceTracker
from gcdtrav.service.runtime.outputs import OutputBuilder
from gcdtrav.service.runtime.schedule.latest_queue import LatestFrameQueue
from gcdtrav.service.runtime.stats import ServiceStats

LOG = __import__("logging").getLogger("test")
JPEG = encode_jpeg(np.full((48, 64, 3), 100, np.uint8))


def envelope(age_s: float, sent_at: float | None = None) -> bytes:
    stamp = time.time() - age_s
    message = ImageEnvelope(stamp=stamp, encoding=PixelEncoding.JPEG, width=64, height=48, data=JPEG, sent_at=sent_at)
    return message.pack()


def admission(**settings: object) -> tuple[Admission, LatestFrameQueue[PendingFrame], ServiceStats, list[tuple]]:
    queue: LatestFrameQueue[PendingFrame] = LatestFrameQueue()
    stats = ServiceStats(LOG)
    freed: list[tuple[str, str, FrameTimes | None]] = []
    service = ServiceSettings.model_validate({"max_payload_bytes": 100_000} | settings)
    gate = Admission(service, SourceTracker(8, 60), queue, stats, lambda *args: freed.append(args))
    return gate, queue, stats, freed


def offer(gate: Admission, payload: bytes, source: str = "r1") -> bool:
    return gate.offer(source, f"gcdtrav/in/{source}", len(payload), lambda: payload, "application/msgpack")


def test_a_stale_frame_is_dropped_at_intake_and_frees_the_slot() -> None:
    gate, queue, stats, freed = admission(max_frame_age_s=5.0, clock="synced")  # a new source: by the clock
    assert not offer(gate, envelope(age_s=10.0, sent_at=5.0))
    [(source, reason, times)] = freed
    assert (source, reason) == ("r1", "stale") and times is not None and times.sent_at == 5.0
    assert offer(gate, envelope(age_s=0.5, sent_at=6.0))  # a fresh one waits, with its times
    _, pending = queue.take(timeout=0)  # type: ignore[misc]
    assert pending.sent_at == 6.0 and pending.stamp == pytest.approx(time.time() - 0.5, abs=1.0)
    status = stats.snapshot(queue.counters()).sources["r1"]
    assert (status.received, status.stale, status.dropped) == (2, 1, 1)  # received = dropped + the waiting one
    assert status.frame_age_ms["p95"] > 5000 and status.bytes_per_s is not None and status.bytes_per_s > 0
    assert stats.snapshot(queue.counters()).dropped_by_reason == {"stale": 1}


@pytest.mark.parametrize("limit", [None, 1e9])
def test_no_limit_or_a_huge_one_keeps_every_frame(limit: float | None) -> None:
    gate, _, _, freed = admission(max_frame_age_s=limit)
    assert offer(gate, envelope(age_s=1e6)) and not freed


def test_a_refused_frame_frees_the_slot_too() -> None:
    gate, _, _, freed = admission(max_payload_bytes=1024)
    assert not offer(gate, envelope(age_s=0.0) + bytes(2000))  # over 1 kB
    assert [reason for _, reason, _ in freed] == ["refused"]


def test_the_worker_grants_at_take_and_drops_what_waited_too_long() -> None:
    settings = ServiceSettings(max_frame_age_s=10.0, reuse={"enabled": False}, schedule={"policy": "round_robin"})
    runtime, sink, credits = assembled(settings)
    queue, stats, worker = runtime.queue, runtime.stats, runtime.worker
    taken, published = credits.grants, sink.put_by_source
    # Admitted fresh (lag 0.5 s), but it waited in the queue for 30 s: stale at take. The fresh frame's age is
    # this test's time to process it, well under 10 s even on a loaded host.
    waited = PendingFrame("r1", "gcdtrav/in/r1", envelope(0.0), "application/msgpack", time.time() - 30.0, lag_s=0.5)
    queue.put("r1", waited)
    worker.start()
    try:
        deadline = time.monotonic() + 60  # a failure's bound
        while not taken and time.monotonic() < deadline:
            time.sleep(0.01)
        queue.put("r1", PendingFrame("r1", "gcdtrav/in/r1", envelope(age_s=0.0), "application/msgpack", time.time()))
        while len(published) < 1 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        worker.stop(time.monotonic() + 5)
    assert len(taken) == 2 and len(published) == 1  # both freed the slot; only the fresh one was computed
    status = stats.snapshot(queue.counters()).sources["r1"]
    assert (status.stale, status.processed) == (1, 1)


@pytest.mark.parametrize(
    ("max_side", "shape"), [(None, (MAP_SIDE, MAP_SIDE)), (4, (4, 4)), (100, (MAP_SIDE, MAP_SIDE))]
)
def test_compact_maps_decode_to_the_maps_within_their_steps(max_side: int | None, shape: tuple[int, int]) -> None:
    frame = processed(height=48, width=64)
    builder = OutputBuilder(ServiceSettings(compact_maps_max_side=max_side), "fake")
    outputs = {output.key: output for output in builder.build(frame, compact=True)}
    assert "gcdtrav/out/r1/front/maps8" not in {o.key for o in builder.build(frame)}  # only when asked
    compact = Maps.from_compact_payload(outputs["gcdtrav/out/r1/front/maps8"].payload)
    full = Maps.from_payload(outputs["gcdtrav/out/r1/front/maps"].payload)
    assert compact.compact and compact.header.map_shape == shape == compact.traversability.shape
    assert compact.header.scale == pytest.approx((64 / shape[1], 48 / shape[0]))
    assert compact.header.stamp == full.header.stamp == 12.5
    if shape == (MAP_SIDE, MAP_SIDE):
        np.testing.assert_allclose(compact.traversability, full.traversability, atol=0.5 / 255 + 1e-6)
        np.testing.assert_allclose(compact.uncertainty, full.uncertainty, atol=0.5 / 255 + 1e-6)
    assert len(outputs["gcdtrav/out/r1/front/maps8"].payload) < len(outputs["gcdtrav/out/r1/front/maps"].payload)
