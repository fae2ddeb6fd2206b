"""The status, assembled from the runtime's parts without a bus: each field from the part that owns it."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
from fakes import Clock, pipeline
from gcdtrav.schemas.anchors import AnchorSet, default_anchor_set
from gcdtrav.schemas.config import Method
from gcdtrav.service.backends.base import BackendDescription
from gcdtrav.service.runtime.fleet.anchor_switch import AnchorSwitch
from gcdtrav.service.runtime.history import FrameHistory
from gcdtrav.service.runtime.intake.clock_offset import ClockOffsets
from gcdtrav.service.runtime.intake.sources import SourceTracker
from gcdtrav.service.runtime.progress import ProgressMonitor
from gcdtrav.service.runtime.schedule.latest_queue import LatestFrameQueue
from gcdtrav.service.runtime.stats import ServiceStats
from gcdtrav.service.runtime.status import StatusParts
from gcdtrav.service.store.sqlite import SqliteStore

from tools.loopback import admit

TWO = AnchorSet.parse(
    {"name": "two", "anchors": [{"concept": "lake", "position": 0.0}, {"concept": "road", "position": 1.0}]}
)


def parts(tmp_path: Path, clock: Clock) -> StatusParts:
    run = pipeline()
    switch = AnchorSwitch(run, SqliteStore(tmp_path / "store.sqlite3"), "box-1", 65536)
    queue: LatestFrameQueue[bytes] = LatestFrameQueue(1000)
    sources = SourceTracker(max_sources=3, idle_s=60.0)
    progress = ProgressMonitor(2.0, clock)
    stats = ServiceStats(logging.getLogger("test"))
    offsets = ClockOffsets(1.0, 5.0)
    return StatusParts("box-1", 100.0, run, switch, queue, FrameHistory(2), stats, sources, progress, offsets)


def test_a_fresh_instance_reports_its_start_set_backend_and_bounds(tmp_path: Path) -> None:
    status = parts(tmp_path, Clock()).status(now=112.5)
    assert (status.instance, status.instances, status.uptime_s) == ("box-1", ["box-1"], 12.5)
    assert (status.model, status.precision, status.precision_reason, status.measuring) == ("fake", "-", "", False)
    assert status.anchor_set_version == default_anchor_set().version
    assert status.anchor_set_accepted_at is None  # the set it started with was never accepted in the fleet
    assert status.method == Method.GCD and status.anchor_sets == {}
    assert (status.queued, status.queued_bytes, status.tracked_sources, status.max_sources) == (0, 0, 0, 3)
    assert status.healthy and status.reason == ""


def test_the_status_follows_each_part(tmp_path: Path) -> None:
    clock = Clock()
    board = parts(tmp_path, clock)
    board.anchors.swap(TWO)
    board.queue.put("r1/front", b"x" * 40, 40)
    admit(board.sources, "r1/front")
    board.stats.rejected("r2/rear", "bad_stamp", "a NaN stamp")
    clock.now = 5.0  # a frame queued and no beat for 5 s > stall_after_s
    board.progress.check(len(board.queue))
    status = board.status(now=101.0, live=["box-2", "box-1"], fleet={"box-1": TWO.version, "box-2": "other"})
    assert status.anchor_set_version == TWO.version and status.anchor_set_accepted_at == pytest.approx(
        board.anchors.head().accepted_at
    )
    assert status.instances == ["box-1", "box-2"] and status.anchor_sets == {"box-1": TWO.version, "box-2": "other"}
    assert (status.queued, status.queued_bytes, status.tracked_sources) == (1, 40, 1)
    assert status.rejected_by_reason == {"bad_stamp": 1} and "a NaN stamp" in status.last_errors[-1]
    assert not status.healthy and status.reason.startswith("stalled")


def test_the_backend_is_read_through_its_description(tmp_path: Path) -> None:
    board = parts(tmp_path, Clock())
    measuring = BackendDescription("auto-model", (224, 224), "fp32", "auto: measuring", measuring=True)
    board.pipeline.backend.describe = lambda: measuring  # type: ignore[method-assign]
    status = board.status(now=100.0)
    assert (status.model, status.precision, status.precision_reason, status.measuring) == (
        "auto-model",
        "fp32",
        "auto: measuring",
        True,
    )
