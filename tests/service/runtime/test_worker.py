"""The worker without a bus: frames in, outputs out, every frame accounted for, also at shutdown."""

from __future__ import annotations

import threading
import time

import pytest
from fakes import assembled, offer, pipeline, png_frame
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.backends.cpus import usable_cpus
from gcdtrav.service.runtime.frames import PendingFrame
from gcdtrav.service.runtime.schedule.latest_queue import LatestFrameQueue
from gcdtrav.service.runtime.stats import ServiceStats

LOG = __import__("logging").getLogger("test")


def worker(threads: int | None, delay_s: float = 0.0):  # type: ignore[no-untyped-def]
    """The service's assembly, every frame inferred in round robin (no glance)."""
    settings = ServiceSettings(threads=threads, reuse={"enabled": False}, schedule={"policy": "round_robin"})
    run = pipeline(delay_s)
    runtime, sink, _ = assembled(settings, run)
    return runtime.worker, runtime, runtime.stats, sink, run


def accounted(stats: ServiceStats, queue: LatestFrameQueue[PendingFrame]) -> dict[str, tuple[int, int]]:
    """Per source: (received, processed + dropped + rejected)."""
    snapshot = stats.snapshot(queue.counters())
    return {name: (s.received, s.processed + s.dropped + s.rejected) for name, s in snapshot.sources.items()}


MODES = [None, 1]  # torch on every CPU (one thread does all), or one fewer (outputs overlap inference)


@pytest.mark.parametrize("threads", MODES)
def test_frames_are_published_and_bad_ones_counted_without_stopping(threads: int | None) -> None:
    if threads is not None and usable_cpus() < 2:
        pytest.skip("overlapping outputs needs two usable CPUs")
    frames, runtime, stats, outputs, _ = worker(threads)
    queue = runtime.queue
    assert frames.overlap_outputs is (threads is not None)
    frames.start()
    offer(runtime, png_frame("a"))
    offer(runtime, PendingFrame("b", "gcdtrav/in/b", b"not an image", "image/png", time.time()))
    offer(runtime, png_frame("c"))
    deadline = time.monotonic() + 60  # a failure's bound: the loop ends when the outputs came
    while len(outputs.sources) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert frames.stop(time.monotonic() + 60)
    assert sorted(outputs.sources) == ["a", "c"]
    snapshot = stats.snapshot(queue.counters())
    assert snapshot.sources["b"].rejected == 1 and snapshot.rejected_by_reason == {"undecodable": 1}
    assert snapshot.sources["b"].refused  # a new source whose frame failed: it never took a slot
    assert all(received == done for received, done in accounted(stats, queue).values())


@pytest.mark.parametrize("threads", MODES)
def test_shutdown_under_load_finishes_the_frame_in_flight_and_counts_the_rest(threads: int | None) -> None:
    if threads is not None and usable_cpus() < 2:
        pytest.skip("overlapping outputs needs two usable CPUs")
    frames, runtime, stats, outputs, run = worker(threads)
    queue = runtime.queue
    release = run.backend.release = threading.Event()  # type: ignore[attr-defined]
    for source in ("a", "b", "c", "d"):
        offer(runtime, png_frame(source))
    frames.start()
    assert run.backend.started.wait(30)  # type: ignore[attr-defined]
    queue.close()
    # The frame in flight is held until the worker is told to stop: with a fixed inference time (0.3 s before),
    # a test thread slower than that on a loaded machine let the worker take the next frame before stop().
    stopped: list[bool] = []
    stopper = threading.Thread(target=lambda: stopped.append(frames.stop(time.monotonic() + 60)))
    stopper.start()
    assert frames._stopping.wait(30)
    release.set()
    stopper.join(90)
    assert stopped == [True]  # the threads ended: nothing can publish after stop
    assert not any(thread.is_alive() for thread in frames._threads)
    outputs.closed = True
    assert len(outputs.sources) == 1  # the frame in flight, not the queue drained
    snapshot = stats.snapshot(queue.counters())
    assert snapshot.dropped_by_reason == {"shutdown": 3}
    assert all(received == done for received, done in accounted(stats, queue).values())


def test_a_frame_finished_after_the_outputs_closed_is_counted_dropped() -> None:
    frames, runtime, stats, outputs, _ = worker(None)
    queue = runtime.queue
    outputs.closed = True
    offer(runtime, png_frame("a"))
    frames.start()
    deadline = time.monotonic() + 60  # a failure's bound: the loop ends when the outputs came
    while not stats.snapshot(queue.counters()).dropped_by_reason and time.monotonic() < deadline:
        time.sleep(0.01)
    assert frames.stop(time.monotonic() + 60)
    assert stats.snapshot(queue.counters()).dropped_by_reason == {"shutdown": 1}
    assert not outputs.sources
