"""`gcdtrav status`'s table without a service: each source's clock as the service learnt it."""

from __future__ import annotations

from gcdtrav.client.operator import clock_offset, status_table
from gcdtrav.schemas.config import Method
from gcdtrav.schemas.messages import ServiceStatus, SourceStatus


def status(sources: dict[str, SourceStatus]) -> ServiceStatus:
    return ServiceStatus(
        instance="box-1",
        uptime_s=10.0,
        model="m",
        anchor_set_version="v",
        method=Method.GCD,
        queued=0,
        sources=sources,
        rejected_by_reason={},
        last_errors=[],
    )


def test_each_source_shows_its_clock_offset_and_clocks_off_by_a_second_are_named() -> None:
    table = status_table(
        [
            status(
                {
                    "behind/front": SourceStatus(clock_offset_s=3600.021),
                    "synced/front": SourceStatus(clock_offset_s=0.012),
                    "bare/cam": SourceStatus(),
                    "bag/cam": SourceStatus(clock_offset_s=1.1e8),
                }
            )
        ]
    )
    rows = {line.split()[0]: line.split() for line in table.splitlines() if line.split()[1:2] == ["box-1"]}
    assert rows["behind/front"][-1] == "+3600.02" and rows["synced/front"][-1] == "+0.01"
    assert rows["bare/cam"][-1] == "-" and rows["bag/cam"][-1] == "+1.1e+08"
    warning = next(line for line in table.splitlines() if line.startswith("clocks off"))
    assert "bag/cam, behind/front (" in warning and "synced/front" not in warning


def test_offsets_at_their_edges() -> None:
    assert clock_offset(None) == "-" and clock_offset(0.0) == "+0.00" and clock_offset(-3600.0) == "-3600.00"
