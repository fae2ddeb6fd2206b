"""Counters by reason, and the rate-limited log lines that go with them."""

from __future__ import annotations

import logging

import pytest
from gcdtrav.service.runtime.frame_age import FrameAgeLimit
from gcdtrav.service.runtime.stats import ServiceStats


def test_stale_frames_are_counted_each_and_logged_once_per_interval_with_what_to_check(
    caplog: pytest.LogCaptureFixture,
) -> None:
    stats = ServiceStats(logging.getLogger("gcdtrav.test"))
    limit = FrameAgeLimit(5.0)
    with caplog.at_level(logging.WARNING, "gcdtrav.test"):
        for _ in range(3):
            stats.stale("r1/front", limit.explain(stamp=1000.0, now=4600.0))
    snapshot = stats.snapshot({})
    assert snapshot.sources["r1/front"].dropped == 3 and snapshot.dropped_by_reason == {"stale": 3}
    assert len(caplog.records) == 1
    assert "captured 3600.0 s ago, over max_frame_age_s = 5 s" in caplog.text and "null" in caplog.text


def test_rejections_log_once_per_reason_but_each_reason_once(caplog: pytest.LogCaptureFixture) -> None:
    stats = ServiceStats(logging.getLogger("gcdtrav.test"))
    with caplog.at_level(logging.WARNING, "gcdtrav.test"):
        for reason in ("undecodable", "undecodable", "oversized"):
            stats.rejected("r1", reason, "detail")
    assert [record.getMessage().split(": ")[1] for record in caplog.records] == ["undecodable", "oversized"]
    assert stats.snapshot({}).rejected_by_reason == {"undecodable": 2, "oversized": 1}
