"""The runtime as the service assembles it (service/runtime/assembly.py), without zenoh: admission with its
rate check first, the glance, the scheduler, the worker, the one hand-off out and the credits."""

from __future__ import annotations

import threading
import time

import pytest
from fakes import Clock, assembled, image, until
from gcdtrav.schemas.images import encode_png
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.runtime.assembly import Runtime
from gcdtrav.service.runtime.frames import PendingFrame
from gcdtrav.service.runtime.outputs import Output
from gcdtrav.service.runtime.schedule.share import Claim

PNG = encode_png(image(32, 32))
OTHER_VIEW = encode_png(255 - image(32, 32))  # every block moved


def offer(runtime: Runtime, source: str, publisher: str | None = "robot", png: bytes = PNG) -> bool:
    """As the bus's subscriber does: the rate check, then the offer."""
    if not runtime.admission.admit(publisher):
        return False
    return runtime.admission.offer(source, f"gcdtrav/in/{source}", len(png), lambda: png, "image/png", None, publisher)


def answered_on_settle(runtime: Runtime) -> tuple[threading.Event, list[Claim | None]]:
    """An event set each time the glance settles a frame, and the claims it settled them with: to infer (a
    claim) or reused (None; its answer follows). The test clears the event before the frame it waits for."""
    settled, claims, settle = threading.Event(), [], runtime.queue.settle

    def settle_and_tell(source: str, item: PendingFrame, claim: Claim | None) -> bool:
        kept = settle(source, item, claim)
        claims.append(claim)
        settled.set()
        return kept

    runtime.queue.settle = settle_and_tell  # type: ignore[method-assign]
    return settled, claims


def test_the_assembled_runtime_infers_a_frame_reuses_an_unchanged_one_and_grants_credits_for_both() -> None:
    runtime, sink, credits = assembled(ServiceSettings(max_frame_age_s=None))  # glance and need share on
    assert runtime.queue.triage and runtime.worker.triage is not None
    runtime.worker.start()
    try:
        assert offer(runtime, "r1")
        until(lambda: len(sink.maps()) == 1)
        assert runtime.reuse._views["r1"].reference is not None  # set before its maps went out
        assert offer(runtime, "r1")
        until(lambda: len(sink.maps()) == 2)
    finally:
        assert runtime.worker.stop(time.monotonic() + 10)
    first, again = sink.maps()
    assert again.header.computed_from == (first.header.stamp, first.header.seq)  # the last maps, not inferred again
    until(lambda: [grant.reason for grant in credits.grants] == ["taken", "unchanged"])
    counts = runtime.stats.snapshot(runtime.queue.counters()).sources["r1"]
    assert counts.processed == 1 and counts.unchanged == 1


@pytest.mark.parametrize("threads", [None, 1])  # one worker thread; an output thread beside inference
def test_a_frame_sent_the_moment_its_maps_are_seen_is_glanced_against_them(threads: int | None) -> None:
    """A robot on credits sends its next frame the moment it sees the maps: the glance's reference is set
    before the maps go out, so that frame, unchanged, is answered with them and never inferred again. The
    sink holds the first maps until the glance has settled the next frame: the worst a loaded host does."""
    runtime, sink, _ = assembled(ServiceSettings(max_frame_age_s=None, threads=threads))
    (settled, _), put, sent = answered_on_settle(runtime), sink.put, []

    def robot_sees_maps(source: str, outputs: list[Output]) -> bool:
        if not sent:  # the first maps: the next frame at once, glanced while they are being put
            sent.append(True)
            settled.clear()  # the first frame's glance set it
            assert offer(runtime, "r1")
            assert settled.wait(60)
        return put(source, outputs)

    sink.put = robot_sees_maps  # type: ignore[method-assign]
    runtime.worker.start()
    try:
        assert offer(runtime, "r1")
        until(lambda: len(sink.maps()) == 2)
    finally:
        assert runtime.worker.stop(time.monotonic() + 10)
    first, again = sink.maps()  # in order: the reused answer never overtakes the maps it repeats
    assert first.header.computed_from is None
    assert again.header.computed_from == (first.header.stamp, first.header.seq)
    counts = runtime.stats.snapshot(runtime.queue.counters()).sources["r1"]
    assert counts.processed == 1 and counts.unchanged == 1


@pytest.mark.parametrize("threads", [None, 1])  # one worker thread; an output thread beside inference
def test_a_reused_frame_is_never_answered_with_the_previous_frame_s_maps(threads: int | None) -> None:
    """The maps kept for reuse and the glance's reference change together. A frame of a new view sent while
    that view's maps are being encoded (the sink held there until the frame is settled and, if reused,
    answered) must never get the old view's maps; one sent the moment the new maps are seen gets them."""
    runtime, sink, _ = assembled(ServiceSettings(max_frame_age_s=None, threads=threads))
    (settled, claims), wants_compact, put = answered_on_settle(runtime), sink.wants_compact, sink.put
    reused_put, sent = threading.Event(), []

    def encoding(source: str) -> bool:  # asked just before a frame's maps are encoded
        if len(sink.maps()) == 1 and not sent:  # the new view's: the next frame of it now
            sent.append("while encoding")
            settled.clear()
            assert offer(runtime, "r1", png=OTHER_VIEW)
            assert settled.wait(60)
            assert claims[-1] is not None or reused_put.wait(60)  # to infer, or answered
        return wants_compact(source)

    def seen(source: str, outputs: list[Output]) -> bool:
        published = put(source, outputs)
        if any(maps.header.computed_from is not None for maps in sink.maps()):
            reused_put.set()
        if len(sink.maps()) == 3 and len(sent) == 1:  # maps of the new view seen: the next frame at once
            sent.append("on seeing the maps")
            assert offer(runtime, "r1", png=OTHER_VIEW)
        return published

    sink.wants_compact, sink.put = encoding, seen  # type: ignore[method-assign]
    runtime.worker.start()
    try:
        assert offer(runtime, "r1")
        until(lambda: len(sink.maps()) == 1)
        assert offer(runtime, "r1", png=OTHER_VIEW)  # a new view: inferred
        until(lambda: len(sink.maps()) == 4)
    finally:
        assert runtime.worker.stop(time.monotonic() + 10)
    old_view, *later = sink.maps()
    new_view = {(maps.header.stamp, maps.header.seq) for maps in later if maps.header.computed_from is None}
    reused = [maps.header.computed_from for maps in later if maps.header.computed_from is not None]
    assert old_view.header.computed_from is None and (old_view.header.stamp, old_view.header.seq) not in reused
    assert reused and all(computed in new_view for computed in reused)
    assert len(sent) == 2
    counts = runtime.stats.snapshot(runtime.queue.counters()).sources["r1"]
    assert counts.processed + counts.unchanged == 4 and counts.unchanged == len(reused)


def test_the_rate_check_is_admissions_first_and_leaves_no_state() -> None:
    runtime, _, _ = assembled(ServiceSettings(intake_rate_per_publisher=1.0, intake_burst_s=1.0))
    assert offer(runtime, "r1", "flooder")
    assert not offer(runtime, "r2", "flooder")  # over its rate: r2 is never looked at
    snapshot = runtime.stats.snapshot(runtime.queue.counters())
    assert snapshot.rejected_by_reason == {"rate_limited": 1} and "r2" not in snapshot.sources
    assert offer(runtime, "r2", "another")  # each publisher has its own bucket


def test_a_forgotten_source_leaves_the_bus_sinks_too() -> None:
    clock = Clock()
    settings = ServiceSettings(reuse={"enabled": False}, schedule={"policy": "round_robin"}, max_frame_age_s=None)
    runtime, sink, _ = assembled(settings, clock=clock)
    assert offer(runtime, "r1")
    _, pending = runtime.queue.take(0)
    inferred = runtime.worker._guarded(pending, runtime.worker._infer, pending)
    runtime.worker._guarded(pending, runtime.worker._finish, inferred)
    assert sink.sources == ["r1"]
    clock.now = settings.source_idle_s + 1
    assert runtime.sources.sweep() == ["r1"] and sink.forgotten == ["r1"]
    assert runtime.credits.ledger.freed("r1", "taken").grant == 0  # numbered afresh


def test_the_watchdogs_tick_puts_the_safe_mask_of_a_stale_grid_once_and_tells_a_stalled_worker() -> None:
    """Runtime.tick, zenoh-free: the jobs the bus's watchdog runs four times a second."""
    from gcdtrav.schemas.settings import GridSettings

    grid = GridSettings.model_validate(
        {"source": "r1", "intrinsics": {"fx": 50, "fy": 50, "cx": 16, "cy": 16, "width": 32, "height": 32},
         "mount": {"z": 1.0, "pitch": 0.6}, "speed": {"stale_s": 1.0}}
    )  # fmt: skip
    clock = Clock(100.0)
    runtime, sink, _ = assembled(ServiceSettings(grids=[grid], stall_after_s=0.5), clock=clock)
    assert runtime.tick() is None and sink.put_by_source == []  # nothing stale or stalled, no mask ever handed out
    state = runtime.grids.sources["r1"]  # type: ignore[union-attr]
    state.speed_mask_at, state.speed_safe = time.time() - 5.0, False  # a live mask, 5 s old: stale
    assert runtime.tick() is None
    keys = [output.key for _, outputs in sink.put_by_source for output in outputs]
    assert "gcdtrav/out/r1/grid/speed_mask" in keys and "gcdtrav/out/r1/grid/speed_limit" in keys
    assert state.speed_safe
    before = len(sink.put_by_source)
    runtime.tick()
    assert len(sink.put_by_source) == before  # put once: the safe mask stays until a live one replaces it
    assert offer(runtime, "r1")  # a frame waits, the worker never started: no beat for longer than stall_after_s
    clock.now += 1.0
    change = runtime.tick()
    assert change is not None and not change.health.healthy
    assert not runtime.readiness(draining=False, in_fleet=True).healthy
