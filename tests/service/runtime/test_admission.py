"""Admission after validation: a new source takes a slot only once a frame of it decodes, so a flood of
invented names can neither fill the slots nor keep a real robot's first frame out."""

from __future__ import annotations

import pytest
from fakes import assembled, image
from gcdtrav.schemas.images import encode_png
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.runtime.candidates import CandidatePool, over_publisher_cap
from gcdtrav.service.runtime.sources import SourcesFull, SourceTracker
from gcdtrav.service.runtime.stats import REFUSED_SOURCES

PNG = encode_png(image(16, 16))
GARBAGE = b"\x89PNG not really"


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


class Service:
    """The runtime as the service assembles it, its worker driven one frame at a time (no threads; no glance:
    every frame goes straight to inference, taken in round robin)."""

    def __init__(self, clock: FakeClock | None = None, **settings: object) -> None:
        settings = {"reuse": {"enabled": False}, "schedule": {"policy": "round_robin"}} | settings
        self.settings = ServiceSettings(max_frame_age_s=None, **settings)  # type: ignore[arg-type]
        runtime, self.sink, _ = assembled(self.settings, clock=clock or FakeClock())
        self.queue, self.stats, self.sources = runtime.queue, runtime.stats, runtime.sources
        self.admission, self.worker = runtime.admission, runtime.worker

    @property
    def published(self) -> list[str]:
        return self.sink.sources

    def offer(self, source: str, payload: bytes = PNG, publisher: str | None = None) -> bool:
        return self.admission.offer(
            source, f"gcdtrav/in/{source}", len(payload), lambda: payload, "image/png", publisher=publisher
        )

    def serve(self, frames: int = 1_000_000) -> list[str]:
        """Take and process up to ``frames`` frames; the sources served, in order."""
        served = []
        for _ in range(frames):
            item = self.queue.take(0)
            if item is None:
                break
            source, pending = item
            served.append(source)
            inferred = self.worker._guarded(pending, self.worker._infer, pending)
            if inferred is not None:
                self.worker._guarded(pending, self.worker._finish, inferred)
        return served

    def snapshot(self):  # type: ignore[no-untyped-def]
        return self.stats.snapshot(self.queue.counters())


def test_a_source_takes_a_slot_only_once_a_frame_decodes() -> None:
    service = Service(max_sources=1)
    assert service.offer("junk", GARBAGE)
    assert len(service.sources) == 0 and "junk" in service.admission.candidates
    service.serve()
    assert len(service.sources) == 0 and len(service.admission.candidates) == 0
    assert service.offer("robot") and service.serve() == ["robot"] and "robot" in service.sources
    snapshot = service.snapshot()
    assert sum(snapshot.rejected_by_reason.values()) == 1 and snapshot.dropped_by_reason == {}
    assert service.published == ["robot"]
    assert [name for name, s in snapshot.sources.items() if not s.refused] == ["robot"]
    junk = snapshot.sources["junk"]  # shown, with why, but it holds no slot (issue 36: it was invisible)
    assert junk.refused and junk.received == junk.rejected == 1 and junk.rejected_by_reason == {"undecodable": 1}
    assert junk.problem.startswith("undecodable: not a decodable image")


def test_a_flood_of_undecodable_names_never_keeps_a_robot_out_and_counts_as_rejected() -> None:
    service = Service(max_sources=1)
    for k in range(1000):
        service.offer(f"flood/{k}", GARBAGE)
    assert len(service.queue) == service.settings.max_candidates == 32
    assert service.offer("robot")
    service.serve()
    assert "robot" in service.sources and service.published == ["robot"]
    snapshot = service.snapshot()
    assert snapshot.dropped_by_reason == {}
    # The robot's frame evicted one more; the 31 still waiting were decoded and refused with their reason.
    assert snapshot.rejected_by_reason == {"candidate_evicted": 1000 - 32 + 1, "undecodable": 31}
    assert [name for name, s in snapshot.sources.items() if not s.refused] == ["robot"]
    refused = [name for name, s in snapshot.sources.items() if s.refused]
    assert 0 < len(refused) <= REFUSED_SOURCES  # the invented names shown are bounded


def test_a_flood_of_decodable_one_frame_names_gives_way_to_a_streaming_robot() -> None:
    clock = FakeClock()
    service = Service(clock, max_sources=4, reclaim_after_s=1.0)
    service.offer("robot")
    service.serve()
    service.offer("robot")  # streaming: its second frame
    for k in range(3):
        service.offer(f"flood/{k}")
    service.serve()
    assert len(service.sources) == 4
    clock.now += 0.5  # the flood's slots are not reclaimable yet: a new name is refused
    assert not service.offer("robot2")
    assert service.snapshot().rejected_by_reason == {"too_many_sources": 1}
    clock.now += 1.0
    for k in range(3, 100):  # the flood goes on: its names reclaim each other's slots, never the robot's
        service.offer(f"flood/{k}")
        service.serve()
        clock.now += 1.0
        assert "robot" in service.sources
    service.offer("robot2")
    service.offer("robot")
    assert sorted(service.serve()) == ["robot", "robot2"]
    assert "robot2" in service.sources and "robot" in service.sources and len(service.sources) == 4
    assert service.published.count("robot") == 3 and service.published.count("robot2") == 1


def test_max_sources_one_is_kept_by_a_streaming_robot() -> None:
    clock = FakeClock()
    service = Service(clock, max_sources=1, reclaim_after_s=0.0)
    service.offer("robot")
    service.serve()
    service.offer("robot")
    service.serve()
    clock.now += 100.0
    assert not service.offer("other")  # a source with two frames is never evicted
    assert service.snapshot().rejected_by_reason == {"too_many_sources": 1}
    assert list(service.sources._last_seen) == ["robot"]


def test_one_frame_sources_are_reclaimed_idlest_first() -> None:
    clock, forgotten = FakeClock(), []
    tracker = SourceTracker(2, 60.0, [forgotten.append], clock=clock, reclaim_after_s=1.0)
    assert tracker.promote("a") is None
    clock.now += 0.5
    assert tracker.promote("b") is None
    with pytest.raises(SourcesFull):
        tracker.promote("c")  # neither has been idle for reclaim_after_s
    clock.now += 0.6  # a idle 1.1 s, b 0.6 s
    assert tracker.promote("c") == "a" and forgotten == ["a"]  # the idlest one-frame source
    assert tracker.promote("c") == "c"  # already tracked


def test_a_candidate_whose_slot_went_is_refused_at_promotion() -> None:
    service = Service(max_sources=1, reclaim_after_s=1000.0)
    service.offer("a")
    service.offer("b")  # both wait: the slot is free
    assert service.serve() == ["a", "b"]
    assert list(service.sources._last_seen) == ["a"] and service.published == ["a"]
    snapshot = service.snapshot()
    assert snapshot.rejected_by_reason == {"too_many_sources": 1} and list(snapshot.sources) == ["a", "b"]
    assert snapshot.sources["b"].refused and snapshot.sources["b"].rejected_by_reason == {"too_many_sources": 1}


def test_candidates_cap_one_keeps_the_newest() -> None:
    service = Service(max_candidates=1)
    service.offer("old")
    service.offer("new")
    assert service.serve() == ["new"] and service.snapshot().rejected_by_reason == {"candidate_evicted": 1}
    pool = CandidatePool(1)
    assert pool.add("a", None) is None and pool.add("a", None) is None and pool.add("b", "p") == "a"
    assert pool.pop("b") == (True, "p") and pool.pop("b") == (False, None)


def test_per_publisher_cap_one_and_no_publisher() -> None:
    service = Service(max_sources_per_publisher=1)
    assert service.offer("a", publisher="robot-session")
    assert not service.offer("b", publisher="robot-session")  # waiting counts too
    assert service.offer("c", publisher="other")
    assert all(service.offer(f"anon/{k}") for k in range(5))  # no source info: not capped
    service.serve()
    assert not service.offer("d", publisher="robot-session")  # tracked counts
    assert service.offer("a", publisher="robot-session")  # its own source again
    assert service.snapshot().rejected_by_reason == {"too_many_sources_per_publisher": 2}
    assert over_publisher_cap("p", 1, 1) and not over_publisher_cap("p", 0, 1)
    uncapped = Service(max_sources_per_publisher=None)
    assert all(uncapped.offer(f"n/{k}", publisher="robot-session") for k in range(20))
    assert not over_publisher_cap(None, 100, 1) and not over_publisher_cap("p", 100, None)


def test_a_candidate_evicted_while_its_frame_is_taken_is_counted_once() -> None:
    service = Service(max_candidates=1)
    service.offer("a", GARBAGE)
    _, pending = service.queue.take(0)  # type: ignore[misc]
    service.offer("b", GARBAGE)  # evicts "a" before the worker marked it taken
    assert service.worker._guarded(pending, service.worker._infer, pending) is None
    assert service.snapshot().rejected_by_reason == {"candidate_evicted": 1}  # not also undecodable
    service.serve()
    service.offer("c", GARBAGE)
    _, pending = service.queue.take(0)  # type: ignore[misc]
    service.admission.taken("c")  # taken: a newer new source no longer evicts it
    service.offer("d", GARBAGE)
    service.worker._guarded(pending, service.worker._infer, pending)
    service.serve()
    assert service.snapshot().rejected_by_reason == {"candidate_evicted": 1, "undecodable": 3}
    assert len(service.admission.candidates) == 0 and all(s.refused for s in service.snapshot().sources.values())
    assert sorted(service.snapshot().sources) == ["b", "c", "d"]  # refused with why; "a" is counted by reason only
