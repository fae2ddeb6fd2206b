"""Liveness by progress: stalled only with work waiting and no beat for stall_after_s; healthy at the next beat."""

from __future__ import annotations

from fakes import Clock
from gcdtrav.service.runtime.progress import ProgressMonitor


def test_idle_worker_is_never_stalled_however_long_it_waits() -> None:
    clock = Clock(100.0)
    monitor = ProgressMonitor(2.0, clock)
    clock.now += 3600
    assert monitor.check(queued=0) is None
    assert monitor.health().healthy


def test_queued_work_without_a_beat_stalls_then_one_beat_recovers() -> None:
    clock = Clock(100.0)
    monitor = ProgressMonitor(2.0, clock)
    clock.now += 2.0
    assert monitor.check(queued=3) is None  # at the bound: not yet
    clock.now += 0.1
    change = monitor.check(queued=3)
    assert change is not None and not change.health.healthy
    assert "2.1 s" in change.health.reason and "3 frame(s) queued" in change.health.reason
    assert not monitor.health().healthy and monitor.health().reason == change.health.reason
    assert monitor.check(queued=3) is None  # reported once
    clock.now += 10
    assert monitor.check(queued=0) is None  # the queue emptied (sources failed over): still stalled
    monitor.beat()
    recovered = monitor.check(queued=0)
    assert recovered is not None and recovered.health.healthy and "10.0 s" in recovered.health.reason
    assert monitor.health().healthy and monitor.health().reason == ""


def test_beats_keep_a_busy_worker_healthy() -> None:
    clock = Clock(100.0)
    monitor = ProgressMonitor(0.5, clock)
    for _ in range(20):
        clock.now += 0.4
        monitor.beat()
        assert monitor.check(queued=1) is None


def test_the_default_never_stalls() -> None:
    clock = Clock(100.0)
    monitor = ProgressMonitor(float("inf"), clock)
    clock.now += 1e9
    assert monitor.check(queued=10) is None
