"""The worker with its glance: unchanged views publish the last maps again, changes are inferred, every
frame is accounted for (received = processed + unchanged + dropped + rejected), and reuse can be off."""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import pytest
from fakes import Clock, RecordingCredits, RecordingSink, assembled, pipeline, processed, until
from gcdtrav.schemas.messages import MapsMessage
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.pipeline import Inference, Pipeline
from gcdtrav.service.runtime.frames import PendingFrame
from gcdtrav.service.runtime.grids import GridOutputs
from gcdtrav.service.runtime.outputs import OutputBuilder
from gcdtrav.service.runtime.schedule.latest_queue import LatestFrameQueue
from gcdtrav.service.runtime.schedule.share import Claim, FrameClass, policy_for
from gcdtrav.service.runtime.stats import ServiceStats
from gcdtrav.service.runtime.triage.change import Glance
from gcdtrav.service.runtime.triage.reuse import Republished, ReuseTracker, Triage
from scenes import jpeg_frame, noisy, scene, with_person

LOG = __import__("logging").getLogger("test")


class Outputs:
    """The triage's hand-off and credits, recorded (for the triage driven by hand)."""

    def __init__(self) -> None:
        self.reused: list[tuple[PendingFrame, Glance]] = []
        self.freed: list[str] = []

    def republish(self, pending: PendingFrame, seen: Glance, fits: Callable[[], bool]) -> Republished:
        if not fits():
            return Republished.SUPERSEDED
        self.reused.append((pending, seen))
        return Republished.PUT


class Answers:
    """What the assembled runtime's sinks were given: maps inferred, maps reused (``computed_from`` set) and the
    reasons of the credits granted without taking the frame (unchanged, refresh)."""

    def __init__(self, sink: RecordingSink, credits: RecordingCredits) -> None:
        self.sink, self.credits = sink, credits

    @property
    def inferred(self) -> list[MapsMessage]:
        return [maps for maps in self.sink.maps() if maps.header.computed_from is None]

    @property
    def reused(self) -> list[MapsMessage]:
        return [maps for maps in self.sink.maps() if maps.header.computed_from is not None]

    @property
    def freed(self) -> list[str]:
        return [grant.reason for grant in self.credits.grants if grant.reason != "taken"]


def serving(run: Pipeline | None = None, **settings: object):  # type: ignore[no-untyped-def]
    """The runtime as the service assembles it (the glance, the need share, the worker, the hand-off out)."""
    runtime, sink, credits = assembled(ServiceSettings.model_validate(settings), run)
    return runtime.worker, runtime.queue, runtime.stats, Answers(sink, credits)


def feed(queue: LatestFrameQueue[PendingFrame], outputs: Answers, frames: list[np.ndarray], source: str = "r1") -> None:
    """One frame at a time, each answered (inferred or reused) before the next: a robot on credits."""

    def answered() -> int:
        return len(outputs.inferred) + len(outputs.reused)

    for image in frames:
        before = answered()
        queue.put(source, jpeg_frame(image, source))
        until(lambda before=before: answered() > before)


def accounted(stats: ServiceStats, queue: LatestFrameQueue[PendingFrame]) -> dict[str, tuple[int, int]]:
    snapshot = stats.snapshot(queue.counters())
    return {
        name: (s.received, s.processed + s.unchanged + s.dropped + s.rejected) for name, s in snapshot.sources.items()
    }


@pytest.mark.parametrize("threads", [None, 1])
def test_a_parked_view_is_inferred_once_then_reused_and_a_change_is_inferred(threads: int | None) -> None:
    worker, queue, stats, outputs = serving(threads=threads)
    worker.start()
    view = scene()
    try:
        feed(queue, outputs, [noisy(view, 5.0, k) for k in range(5)] + [with_person(view), with_person(view)])
    finally:
        assert worker.stop(time.monotonic() + 10)
    assert len(outputs.inferred) == 2  # the first view, the person
    assert len(outputs.reused) == 5 and outputs.freed.count("unchanged") == 5
    snapshot = stats.snapshot(queue.counters())
    assert snapshot.sources["r1"].unchanged == 5 and snapshot.sources["r1"].processed == 2
    assert all(received == done for received, done in accounted(stats, queue).values())


def test_reuse_off_infers_every_frame() -> None:
    worker, queue, stats, outputs = serving(reuse={"enabled": False})
    worker.start()
    try:
        feed(queue, outputs, [scene()] * 4)
    finally:
        assert worker.stop(time.monotonic() + 10)
    assert len(outputs.inferred) == 4 and not outputs.reused
    assert all(received == done for received, done in accounted(stats, queue).values())


def test_a_refresh_is_marked_for_the_scheduler_and_news_is_not(monkeypatch: pytest.MonkeyPatch) -> None:
    """The scheduler lets a refresh (max_reuse_s reached, the view unchanged) yield; the triage's claim says
    which."""
    worker, queue, _, outputs = serving(reuse={"max_reuse_s": 0.2})
    marks: list[bool] = []
    settle = queue.settle

    def marking(source: str, item: PendingFrame, claim: Claim | None) -> bool:
        marks.extend([] if claim is None else [claim.kind is FrameClass.REFRESH])
        return settle(source, item, claim)

    monkeypatch.setattr(queue, "settle", marking)
    worker.start()
    view = scene()
    try:
        feed(queue, outputs, [view])
        time.sleep(0.3)
        feed(queue, outputs, [noisy(view, 5.0, 1), with_person(view)])
    finally:
        assert worker.stop(time.monotonic() + 10)
    assert marks == [False, True, False]  # the first view, its refresh, the person
    assert len(outputs.inferred) == 3 and not outputs.reused


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread niceness is Linux's")
@pytest.mark.parametrize("nice", [0, 7, 30])
def test_the_glance_thread_yields_the_cores_to_inference(nice: int) -> None:
    """Its niceness is the service's plus glance_nice (capped at 19); 0 leaves it alone."""
    if nice > 19:
        with pytest.raises(ValueError, match="glance_nice"):
            serving(reuse={"glance_nice": nice})
        return
    own = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    worker, *_ = serving(reuse={"glance_nice": nice})
    worker.start()
    try:
        triage = next(t for t in threading.enumerate() if t.name == "gcdtrav-triage")
        assert triage.native_id is not None
        until(lambda: os.getpriority(os.PRIO_PROCESS, triage.native_id) == min(19, own + nice))  # type: ignore[arg-type]
        infer = next(t for t in threading.enumerate() if t.name == "gcdtrav-infer")
        assert os.getpriority(os.PRIO_PROCESS, infer.native_id) == own  # type: ignore[arg-type]
    finally:
        assert worker.stop(time.monotonic() + 10)


def test_a_hung_inference_is_seen_while_parked_views_are_still_answered() -> None:
    """Answering unchanged views is not inference's progress: the moving robot waiting behind a hung
    inference must fail over (the watchdog's stall) even while a parked robot's frames are reused."""
    hang, release = threading.Event(), threading.Event()
    run = pipeline()
    infer = run.infer

    def hanging_infer(image: np.ndarray) -> Inference:
        if hang.is_set():
            release.wait(20)
        return infer(image)

    run.infer = hanging_infer  # type: ignore[method-assign]
    worker, queue, _, outputs = serving(run=run, stall_after_s=0.3)
    progress = worker.progress
    worker.start()
    view, stalled = scene(), []
    try:
        feed(queue, outputs, [view], "parked")
        hang.set()
        queue.put("moving", jpeg_frame(scene(1), "moving"))  # taken, and its inference hangs
        until(lambda: not queue.has_ready("moving") and len(queue) == 0)
        queue.put("moving", jpeg_frame(scene(1, shift=24), "moving"))  # waits behind it
        deadline = time.monotonic() + 60  # a bound on failure only: a loaded host may see the stall at once
        while not (stalled and len(outputs.reused) >= 3) and time.monotonic() < deadline:
            reused = len(outputs.reused)
            queue.put("parked", jpeg_frame(noisy(view, 4.0, len(outputs.reused)), "parked"))
            until(lambda reused=reused: len(outputs.reused) > reused)  # still answered
            change = progress.check(queued=len(queue))
            stalled += [change] if change is not None and not change.health.healthy else []
    finally:
        release.set()
        assert worker.stop(time.monotonic() + 10)
    assert stalled, "a hung inference hidden by reused frames"
    assert len(outputs.reused) >= 3


def test_unchanged_frames_take_a_waiting_refresh_s_place_and_the_replaced_one_is_answered() -> None:
    """A refresh that yields for long must not infer a frame that waited into staleness: each newer unchanged
    frame takes its place in line, the older one is answered with the last maps, stamps stay in order."""
    config = ServiceSettings.model_validate({"reuse": {"max_reuse_s": 1.0}})
    clock, stats, outputs = Clock(), ServiceStats(LOG), Outputs()
    tracker = ReuseTracker(config.reuse, config.schedule, clock=clock)
    queue: LatestFrameQueue[PendingFrame] = LatestFrameQueue(
        policy=policy_for(config.schedule), triage=True, clock=clock
    )
    triage = Triage(queue, tracker, config, stats, outputs.republish, lambda p, reason: outputs.freed.append(reason))
    view, answered = scene(), []
    frames = [jpeg_frame(noisy(view, 4.0, k), "parked", received_at=100.0 + k) for k in range(6)]
    queue.put("parked", frames[0])
    assert triage.next_reusable(0) is None  # the first view: to infer
    taken = queue.take(0)
    assert taken is not None and taken[1] is frames[0]
    tracker.inferred("parked", frames[0], view)
    clock.now += 2.0  # past max_reuse_s: the next frame is a refresh
    queue.put("parked", frames[1])
    assert triage.next_reusable(0) is None and queue.has_ready("parked")
    for frame in frames[2:]:  # the refresh yields (movers elsewhere): unchanged frames keep arriving
        clock.now += 0.2
        queue.put("parked", frame)
        reusable = triage.next_reusable(0)
        assert reusable is not None
        answered.append(reusable[0])
        triage.reuse(reusable)
    assert answered == frames[1:5]  # each answered when the next one took its place
    assert [seen.stamp for _, seen in outputs.reused] == sorted(seen.stamp for _, seen in outputs.reused)
    taken = queue.take(0)
    assert taken is not None and taken[1] is frames[5]  # the refresh infers the newest view
    assert outputs.freed == ["refresh"] + ["unchanged"] * 4
    counters = queue.counters()["parked"]
    assert counters.received == 6 and counters.dropped == 0 and len(queue) == 0 and queue.nbytes == 0


def test_an_unchanged_frame_behind_a_refresh_taken_meanwhile_is_answered_itself() -> None:
    queue: LatestFrameQueue[str] = LatestFrameQueue(triage=True)
    queue.put("a", "refresh")
    assert queue.take_untriaged(0) == ("a", "refresh") and queue.settle("a", "refresh", Claim(FrameClass.REFRESH))
    queue.put("a", "next")
    assert queue.take_untriaged(0) == ("a", "next")
    assert queue.take(0) == ("a", "refresh")  # the worker took the refresh between the glance and its verdict
    assert queue.settle_in_line("a", "next") == "next" and len(queue) == 0
    queue.put("a", "newer")
    assert queue.settle_in_line("a", "older") is None  # not the arrival: nothing changes
    assert len(queue) == 1


@pytest.mark.parametrize(
    "kinds", [("parked",), ("moving",), ("parked", "moving")], ids=["all parked", "all moving", "mixed"]
)
@pytest.mark.parametrize("infer_s", [0.0, 0.3], ids=["this host", "a slow host"])
def test_fleets_under_load_are_accounted_for(kinds: tuple[str, ...], infer_s: float) -> None:
    """Several sources streaming faster than the answers: replaced frames are dropped, none lost; a parked
    source is inferred once (well within max_reuse_s, however slow the host), a moving one at every turn it
    gets. Each source's first frame is inferred before the stream: a frame glanced while its source's first
    inference runs has no view to compare with and is inferred too, which a slow host would otherwise turn
    into a second inference of a parked robot."""
    run = pipeline()
    infer = run.infer

    def slow_infer(image: np.ndarray) -> Inference:
        time.sleep(infer_s)  # a loaded CI host: each inference outlasts the next frames' glances
        return infer(image)

    run.infer = slow_infer  # type: ignore[method-assign]
    worker, queue, stats, _ = serving(run=run, reuse={"max_reuse_s": 3600.0})
    worker.start()

    def first_frames_inferred() -> bool:
        sources = stats.snapshot(queue.counters()).sources
        return len(sources) == 3 * len(kinds) and all(s.processed == 1 for s in sources.values())

    try:
        for k in range(30):
            if k == 1:
                until(first_frames_inferred)
            for robot in range(3):
                if "parked" in kinds:
                    queue.put(f"parked{robot}", jpeg_frame(noisy(scene(robot), 4.0, k), f"parked{robot}"))
                if "moving" in kinds:
                    queue.put(f"moving{robot}", jpeg_frame(scene(robot, shift=12 * k), f"moving{robot}"))
            time.sleep(0.01)
        until(lambda: len(queue) == 0)
    finally:
        assert worker.stop(time.monotonic() + 10)
    snapshot = stats.snapshot(queue.counters())
    for robot in range(3):
        if "parked" in kinds:
            parked = snapshot.sources[f"parked{robot}"]
            assert parked.unchanged > 0 and parked.processed == 1
        if "moving" in kinds:
            moving = snapshot.sources[f"moving{robot}"]
            assert moving.processed > 1 and moving.unchanged == 0
    assert all(received == done for received, done in accounted(stats, queue).values())


def test_a_reused_frame_republishes_the_maps_without_feeding_the_grid() -> None:
    grid = {
        "source": "r1/front",
        "intrinsics": {"fx": 40, "fy": 40, "cx": 32, "cy": 24, "width": 64, "height": 48},
        "mount": {"z": 1.0, "pitch": 0.5},
        "size_m": 6.0,
        "resolution_m": 0.5,
    }
    settings = ServiceSettings.model_validate({"grids": [grid], "instance": "box"})
    grids = GridOutputs(settings.grids, 13, "box", settings.risk)
    builder = OutputBuilder(settings, "fake")
    done = processed()
    maps = done.result.maps
    done = replace(done, grid=grids.fuse(done.source, done.record, maps.weights, maps.match))  # as the worker does
    first = {o.key: o for o in builder.build(done, compact=True)}
    assert "gcdtrav/out/r1/front/grid" in first and grids.sources["r1/front"].seq == 0
    later = jpeg_frame(scene(), "r1/front", received_at=20.0)
    reused = {o.key: o for o in builder.reused(later, 19.5, "cam", compact=True)}
    assert set(reused) == {"gcdtrav/out/r1/front/maps", "gcdtrav/out/r1/front/maps8"}
    assert grids.sources["r1/front"].seq == 0  # no new evidence
    header = MapsMessage.unpack(reused["gcdtrav/out/r1/front/maps"].payload).header
    original = MapsMessage.unpack(first["gcdtrav/out/r1/front/maps"].payload)
    assert (header.stamp, header.order, header.seq) == (19.5, (19.5, 20.0), 0)
    assert header.computed_from == (12.5, 0) and header.key == later.key
    again = MapsMessage.unpack(reused["gcdtrav/out/r1/front/maps"].payload)
    assert again.traversability_png == original.traversability_png
    chained = MapsMessage.unpack(builder.reused(later, 21.0, "cam")[0].payload).header
    assert chained.computed_from == (12.5, 0)  # always the inferred frame, never a reused one
    builder.forget("r1/front")
    assert builder.reused(later, 22.0, "cam") == []


def test_nothing_is_kept_for_reuse_when_reuse_is_off() -> None:
    builder = OutputBuilder(ServiceSettings(reuse={"enabled": False}), "fake")  # type: ignore[arg-type]
    builder.build(processed())
    assert builder.reused(jpeg_frame(scene(), "r1/front"), 1.0, "") == []
