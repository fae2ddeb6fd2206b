"""The runtime as the service assembles it (service/runtime/assembly.py), without zenoh: admission with its
rate check first, the glance, the scheduler, the worker, the one hand-off out and the credits."""

from __future__ import annotations

import time
from collections.abc import Callable

from fakes import Clock, assembled, image
from gcdtrav.schemas.images import encode_png
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.runtime.assembly import Runtime

PNG = encode_png(image(32, 32))


def offer(runtime: Runtime, source: str, publisher: str | None = "robot") -> bool:
    """As the bus's subscriber does: the rate check, then the offer."""
    if not runtime.admission.admit(publisher):
        return False
    return runtime.admission.offer(source, f"gcdtrav/in/{source}", len(PNG), lambda: PNG, "image/png", None, publisher)


def until(condition: Callable[[], bool], timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert condition()


def test_the_assembled_runtime_infers_a_frame_reuses_an_unchanged_one_and_grants_credits_for_both() -> None:
    runtime, sink, credits = assembled(ServiceSettings(max_frame_age_s=None))  # glance and need share on
    assert runtime.queue.triage and runtime.worker.triage is not None
    runtime.worker.start()
    try:
        assert offer(runtime, "r1")
        until(lambda: len(sink.maps()) == 1)
        # the glance's reference is the inferred frame (set just after its maps go out)
        until(lambda: runtime.reuse._views["r1"].reference is not None)
        assert offer(runtime, "r1")
        until(lambda: len(sink.maps()) == 2)
    finally:
        assert runtime.worker.stop(time.monotonic() + 10)
    first, again = sink.maps()
    assert again.header.computed_from == (first.header.stamp, first.header.seq)  # the last maps, not inferred again
    until(lambda: [grant.reason for grant in credits.grants] == ["taken", "unchanged"])
    counts = runtime.stats.snapshot(runtime.queue.counters()).sources["r1"]
    assert counts.processed == 1 and counts.unchanged == 1


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
