"""Memory follows from the settings, whatever sources the robots (or a hostile peer) invent."""

from __future__ import annotations

import itertools
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import textured_image
from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.schemas.keys import input_key
from gcdtrav.service.runtime.errors import QueryError
from gcdtrav.service.runtime.history import FrameHistory, FrameRecord
from gcdtrav.service.runtime.intake.sources import SWEEP_INTERVAL_S, SourceTracker
from gcdtrav.service.runtime.schedule.latest_queue import LatestFrameQueue, PendingBudgetExceeded
from gcdtrav.service.runtime.stats import REFUSED_SOURCES
from zenoh_helpers import connecting_config, service_reachable, subscribed_elsewhere, wait_until


def record(seq: int, n: int = 4, side: int = 8) -> FrameRecord:
    weights = np.full((n, side, side), 1 / n, np.float16)
    return FrameRecord(seq, float(seq), "cam", weights, default_anchor_set(), (side, side))


FRAME_BYTES = record(0).weights.nbytes


def test_history_stays_within_its_budget_evicting_the_oldest_frame_of_any_source() -> None:
    history = FrameHistory(depth=4, budget_bytes=int(2.5 * FRAME_BYTES))
    history.add("a", record(0))
    history.add("b", record(0))
    history.add("a", record(1))  # over budget: a/0, the oldest of all, goes
    assert history.nbytes == 2 * FRAME_BYTES
    with pytest.raises(QueryError, match=r"seq 0 of 'a' is not kept .*budget of 0 MB"):
        history.get("a", 0)
    assert history.get("b", 0).seq == 0 and history.get("a", None).seq == 1
    for k in range(100):
        history.add(f"churn{k}", record(0))
        assert history.nbytes <= history.budget_bytes  # type: ignore[operator]
    with pytest.raises(QueryError, match=r"unknown source 'a'.*evicted"):
        history.get("a", None)


def test_history_depth_stays_a_cap_per_source() -> None:
    history = FrameHistory(depth=2, budget_bytes=None)
    for seq in range(5):
        history.add("a", record(seq))
    assert history.nbytes == 2 * FRAME_BYTES
    assert history.get("a", 3).seq == 3
    with pytest.raises(QueryError, match="seq 2 of 'a' is not kept"):
        history.get("a", 2)
    history.forget("a")
    assert history.nbytes == 0
    with pytest.raises(QueryError, match="unknown source 'a'"):
        history.get("a", None)


def test_pending_frames_stay_within_their_byte_budget_and_a_refusal_keeps_the_queue() -> None:
    queue: LatestFrameQueue[str] = LatestFrameQueue(max_bytes=100)
    assert queue.put("a", "a0", 60)
    assert not queue.put("a", "a1", 90)  # replaces a0: 90 bytes pending, within the budget
    with pytest.raises(PendingBudgetExceeded, match="over 100 bytes"):
        queue.put("b", "b0", 20)
    assert queue.nbytes == 90 and len(queue) == 1
    assert queue.take(0) == ("a", "a1") and queue.nbytes == 0
    assert queue.put("b", "b0", 20) and queue.nbytes == 20
    queue.forget("b")
    assert queue.nbytes == 0 and len(queue) == 0 and queue.counters() == {"a": queue.counters()["a"]}


def test_a_flood_of_new_sources_gets_at_most_every_other_turn() -> None:
    queue: LatestFrameQueue[int] = LatestFrameQueue()
    for name in ("robot1", "robot2"):
        queue.put(name, 0)
        queue.put(name, 1)  # streaming: a second frame already replaced the first
    for k in range(20):
        queue.put(f"churn/{k}", 0)  # one frame each, arriving before the robots' next ones
    served = []
    for _ in range(12):
        source, _ = queue.take(0)  # type: ignore[misc]
        served.append(source)
        if source.startswith("robot"):
            queue.put(source, 2)  # the robot's next frame
    robots = [s for s in served if s.startswith("robot")]
    # robot1, robot2 (waiting longest), then the flood alternates with the robots, who share their half evenly.
    assert served[:3] == ["robot1", "robot2", "churn/0"]
    assert all(a.startswith("robot") != b.startswith("robot") for a, b in itertools.pairwise(served[1:]))
    assert len(robots) == 7 and abs(robots.count("robot1") - robots.count("robot2")) <= 1


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_tracker_caps_new_sources_forgets_idle_ones_and_never_evicts_active_ones() -> None:
    clock, forgotten = FakeClock(), []
    tracker = SourceTracker(max_sources=2, idle_s=10.0, on_forget=[forgotten.append], clock=clock)
    assert admit(tracker, "a") and admit(tracker, "b")
    assert not admit(tracker, "c")  # over the cap: refused, "a" and "b" untouched
    assert "a" in tracker and "c" not in tracker and len(tracker) == 2
    clock.now += 6.0
    assert admit(tracker, "a")  # "a" stays active
    clock.now += 6.0  # "b" idle for 12 s, "a" for 6 s
    assert tracker.sweep() == ["b"] and forgotten == ["b"]
    assert admit(tracker, "c") and len(tracker) == 2
    assert tracker.sweep() == []  # at most once a second
    clock.now += SWEEP_INTERVAL_S + 10.5
    assert sorted(tracker.sweep()) == ["a", "c"] and len(tracker) == 0


pytest.importorskip("torch")

from gcdtrav.client import ServiceError, TraversabilityClient  # noqa: E402
from gcdtrav.schemas.settings import ServiceSettings  # noqa: E402

from tools.loopback import admit, anchor_set_at_start, in_process_service  # noqa: E402


def test_service_caps_sources_reports_them_and_forgets_idle_ones(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    # source_idle_s: the checks of the tracked sources below come within it (seconds on a loaded machine)
    settings = ServiceSettings(
        state_dir=tmp_path,
        instance="bounded",
        max_sources=3,
        source_idle_s=5.0,
        reclaim_after_s=60,
        preview=False,
    )
    with in_process_service(tiny_backend, settings, anchor_set_at_start(settings)) as (service, port):
        client = TraversabilityClient(config=connecting_config(port), timeout=5.0)
        try:
            assert wait_until(lambda: service_reachable(client), 60)
            assert subscribed_elsewhere(client.session, input_key(client.input_prefix, "r1/cam")), "the inputs"
            image = textured_image(48, 64)
            for k in range(5):  # a robot that names every frame anew
                client.publish_image(f"r1/frame_{k:06d}", image)
                time.sleep(0.05)
            assert wait_until(lambda: sum(s.processed for s in client.status().sources.values()) == 3, 60)
            status = client.status()
            assert status.tracked_sources == 3 and status.max_sources == 3
            assert status.rejected_by_reason.get("too_many_sources") == 2
            tracked = sorted(name for name, source in status.sources.items() if not source.refused)
            assert tracked == [f"r1/frame_{k:06d}" for k in range(3)]  # refused ones hold no slot
            assert 0 < status.history_bytes <= status.history_budget_bytes == 512_000_000
            assert client.patch("r1/frame_000000", 1, 1).seq == 0
            # Idle for longer than source_idle_s: forgotten, with history, counters and publishers.
            assert wait_until(lambda: client.status().tracked_sources == 0, 30)
            status = client.status()
            assert status.sources == {} and status.history_bytes == 0
            assert not service.outputs._publishers
            with pytest.raises(ServiceError, match=r"unknown source 'r1/frame_000000'.*evicted"):
                client.patch("r1/frame_000000", 1, 1)
            client.publish_image("r1/frame_000004", image)  # room again: a new source is served
            assert wait_until(lambda: "r1/frame_000004" in client.status().sources, 60)
        finally:
            client.close()


def test_a_publisher_that_invents_names_is_capped(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    """Our client sets zenoh's source info on every frame: the service caps the sources of its session."""
    settings = ServiceSettings(state_dir=tmp_path, instance="capped", max_sources_per_publisher=2, preview=False)
    with in_process_service(tiny_backend, settings, anchor_set_at_start(settings)) as (_, port):
        client = TraversabilityClient(config=connecting_config(port), timeout=5.0)
        try:
            assert wait_until(lambda: service_reachable(client), 60)
            assert subscribed_elsewhere(client.session, input_key(client.input_prefix, "r1/cam")), "the inputs"
            for k in range(4):
                client.publish_image(f"r1/frame_{k}", textured_image(48, 64))
            assert wait_until(lambda: client.status().rejected_by_reason.get("too_many_sources_per_publisher") == 2, 60)
            assert wait_until(lambda: sum(s.processed for s in client.status().sources.values()) == 2, 60)
            assert sorted(client.status().sources) == ["r1/frame_0", "r1/frame_1"]
        finally:
            client.close()


def test_a_flood_of_undecodable_names_is_rejected_by_reason_and_a_robot_still_served(  # type: ignore[no-untyped-def]
    tiny_backend, tmp_path: Path
) -> None:
    settings = ServiceSettings(state_dir=tmp_path, instance="flooded", max_sources=1, max_candidates=4, preview=False)
    with in_process_service(tiny_backend, settings, anchor_set_at_start(settings)) as (_, port):
        client = TraversabilityClient(config=connecting_config(port), timeout=5.0)
        try:
            assert wait_until(lambda: service_reachable(client), 60)
            assert subscribed_elsewhere(client.session, input_key(client.input_prefix, "r1/cam")), "the inputs"
            for k in range(200):  # raw puts without source info: not capped per publisher
                client.session.put(f"gcdtrav/in/junk/{k}", b"\x89PNG not an image")
            client.publish_image("r1/cam", textured_image(48, 64))
            assert wait_until(lambda: client.status().sources.get("r1/cam", None) is not None, 60)
            assert wait_until(lambda: client.status().sources["r1/cam"].processed == 1, 60)
            status = client.status()
            assert sum(status.rejected_by_reason.values()) == 200 and "candidate_evicted" in status.rejected_by_reason
            assert status.dropped_by_reason == {} and status.tracked_sources == 1
            assert [name for name, source in status.sources.items() if not source.refused] == ["r1/cam"]
            refused = [source for source in status.sources.values() if source.refused]
            assert len(refused) <= REFUSED_SOURCES and all(s.rejected_by_reason == {"undecodable": 1} for s in refused)
        finally:
            client.close()
