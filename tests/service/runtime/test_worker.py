"""The worker without a bus: frames in, outputs out, every frame accounted for, also at shutdown."""

from __future__ import annotations

import time

import pytest
from fakes import pipeline, png_frame
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.backends.cpus import usable_cpus
from gcdtrav.service.runtime.frames import PendingFrame, ProcessedFrame
from gcdtrav.service.runtime.history import FrameHistory
from gcdtrav.service.runtime.latest_queue import LatestFrameQueue
from gcdtrav.service.runtime.sources import SourceTracker
from gcdtrav.service.runtime.stats import ServiceStats
from gcdtrav.service.runtime.worker import FrameWorker

LOG = __import__("logging").getLogger("test")


class Outputs:
    """Records what was published; refuses after close(), as the bus's outputs do."""

    def __init__(self) -> None:
        self.published: list[ProcessedFrame] = []
        self.closed = False

    def publish(self, done: ProcessedFrame) -> bool:
        if self.closed:
            return False
        self.published.append(done)
        return True


def worker(threads: int | None, delay_s: float = 0.0):  # type: ignore[no-untyped-def]
    queue: LatestFrameQueue[PendingFrame] = LatestFrameQueue()
    stats, outputs = ServiceStats(LOG), Outputs()
    settings = ServiceSettings(threads=threads)
    run = pipeline(delay_s)
    frames = FrameWorker(queue, run, FrameHistory(2), stats, SourceTracker(8, 60), settings, outputs.publish)
    return frames, queue, stats, outputs, run


def accounted(stats: ServiceStats, queue: LatestFrameQueue[PendingFrame]) -> dict[str, tuple[int, int]]:
    """Per source: (received, processed + dropped + rejected)."""
    snapshot = stats.snapshot(queue.counters())
    return {name: (s.received, s.processed + s.dropped + s.rejected) for name, s in snapshot.sources.items()}


MODES = [None, 1]  # torch on every CPU (one thread does all), or one fewer (outputs overlap inference)


@pytest.mark.parametrize("threads", MODES)
def test_frames_are_published_and_bad_ones_counted_without_stopping(threads: int | None) -> None:
    if threads is not None and usable_cpus() < 2:
        pytest.skip("overlapping outputs needs two usable CPUs")
    frames, queue, stats, outputs, _ = worker(threads)
    assert frames.overlap_outputs is (threads is not None)
    frames.start()
    queue.put("a", png_frame("a"))
    queue.put("b", PendingFrame("b", "gcdtrav/in/b", b"not an image", "image/png", time.time()))
    queue.put("c", png_frame("c"))
    deadline = time.monotonic() + 10
    while len(outputs.published) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert frames.stop(time.monotonic() + 10)
    assert sorted(done.source for done in outputs.published) == ["a", "c"]
    snapshot = stats.snapshot(queue.counters())
    assert snapshot.sources["b"].rejected == 1 and snapshot.rejected_by_reason == {"undecodable": 1}
    assert all(received == done for received, done in accounted(stats, queue).values())


@pytest.mark.parametrize("threads", MODES)
def test_shutdown_under_load_finishes_the_frame_in_flight_and_counts_the_rest(threads: int | None) -> None:
    if threads is not None and usable_cpus() < 2:
        pytest.skip("overlapping outputs needs two usable CPUs")
    frames, queue, stats, outputs, run = worker(threads, delay_s=0.3)
    for source in ("a", "b", "c", "d"):
        queue.put(source, png_frame(source))
    frames.start()
    assert run.backend.started.wait(5)  # type: ignore[attr-defined]
    queue.close()
    assert frames.stop(time.monotonic() + 10)
    outputs.closed = True
    published = len(outputs.published)
    assert published == 1  # the frame in flight, not the queue drained
    snapshot = stats.snapshot(queue.counters())
    assert snapshot.dropped_by_reason == {"shutdown": 3}
    assert all(received == done for received, done in accounted(stats, queue).values())
    time.sleep(0.4)
    assert len(outputs.published) == published  # nothing after stop


def test_a_frame_finished_after_the_outputs_closed_is_counted_dropped() -> None:
    frames, queue, stats, outputs, _ = worker(None)
    outputs.closed = True
    queue.put("a", png_frame("a"))
    frames.start()
    deadline = time.monotonic() + 10
    while not stats.snapshot(queue.counters()).dropped_by_reason and time.monotonic() < deadline:
        time.sleep(0.01)
    assert frames.stop(time.monotonic() + 10)
    assert stats.snapshot(queue.counters()).dropped_by_reason == {"shutdown": 1}
    assert not outputs.published
