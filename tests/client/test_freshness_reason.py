"""A stale change names what the service last said of the source's frames; a fresh one names nothing."""

from __future__ import annotations

from gcdtrav.client.freshness import FreshnessWatch


def test_a_stale_change_carries_the_services_reason_and_fresh_again_clears_it() -> None:
    now = [100.0]
    watch = FreshnessWatch(1.0, clock=lambda: now[0])
    watch.watch("r1/front")
    watch.note_reason("r1/front", "stale: captured 3600.0 s ago, over max_frame_age_s = 5 s")
    now[0] += 2.0
    [change] = watch.check()
    assert change.stale and change.reason == "stale: captured 3600.0 s ago, over max_frame_age_s = 5 s"
    watch.observe("r1/front", now[0])
    watch.note_reason("r1/front", None)  # maps published: the next credit says nothing is wrong
    [fresh] = watch.check()
    assert not fresh.stale and fresh.reason is None
    now[0] += 2.0
    [again] = watch.check()
    assert again.stale and again.reason is None  # stale for another cause the service did not name (a dead link)


def test_a_reason_heard_after_going_stale_is_reported_once() -> None:
    now = [0.0]
    watch = FreshnessWatch(1.0, clock=lambda: now[0])
    watch.watch("cam")
    now[0] = 2.0
    assert [(c.stale, c.reason) for c in watch.check()] == [(True, None)]  # stale before the service said why
    watch.note_reason("cam", "undecodable: not a decodable image")
    assert [(c.stale, c.reason) for c in watch.check()] == [(True, "undecodable: not a decodable image")]
    assert watch.check() == []  # told once
