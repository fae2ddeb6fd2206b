"""Counters by reason, and the rate-limited log lines that go with them."""

from __future__ import annotations

import logging

import pytest
from gcdtrav.service.runtime.intake.freshness import Freshness
from gcdtrav.service.runtime.stats import ServiceStats


def test_stale_frames_are_counted_each_and_logged_once_per_interval_with_what_to_check(
    caplog: pytest.LogCaptureFixture,
) -> None:
    stats = ServiceStats(logging.getLogger("gcdtrav.test"))
    synced = Freshness(5.0, None, "synced")
    with caplog.at_level(logging.WARNING, "gcdtrav.test"):
        for _ in range(3):
            refusal = synced.at_intake("r1/front", 1000.0, 4600.0).refusal
            assert refusal is not None
            stats.stale("r1/front", str(refusal.detail))
    snapshot = stats.snapshot({})
    assert snapshot.sources["r1/front"].dropped == 3 and snapshot.dropped_by_reason == {"stale": 3}
    assert len([r for r in caplog.records if r.name == "gcdtrav.test"]) == 1
    assert "captured 3600.0 s ago by the service's clock, over max_frame_age_s = 5 s" in caplog.text
    assert "clock: estimated" in caplog.text and "null" in caplog.text


def test_refusals_before_reading_count_by_reason_only_and_build_their_detail_once_per_interval(
    caplog: pytest.LogCaptureFixture,
) -> None:
    stats, built = ServiceStats(logging.getLogger("gcdtrav.test")), []
    with caplog.at_level(logging.WARNING, "gcdtrav.test"):
        for _ in range(1000):
            stats.rejected_unread("rate_limited", lambda: built.append(1) or "publisher p")  # type: ignore[func-returns-value]
    snapshot = stats.snapshot({})
    assert snapshot.rejected_by_reason == {"rate_limited": 1000} and snapshot.sources == {}
    assert len(built) == 1 and len(caplog.records) == 1 and "rate_limited: publisher p" in caplog.text


def test_rejections_log_once_per_reason_but_each_reason_once(caplog: pytest.LogCaptureFixture) -> None:
    stats = ServiceStats(logging.getLogger("gcdtrav.test"))
    with caplog.at_level(logging.WARNING, "gcdtrav.test"):
        for reason in ("undecodable", "undecodable", "oversized"):
            stats.rejected("r1", reason, "detail")
    assert [record.getMessage().split(": ")[1] for record in caplog.records] == ["undecodable", "oversized"]
    assert stats.snapshot({}).rejected_by_reason == {"undecodable": 2, "oversized": 1}
