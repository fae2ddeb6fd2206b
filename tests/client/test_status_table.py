"""`gcdtrav status`'s table, without a service: every source in full, columns under their headers, and why."""

from __future__ import annotations

import re

from gcdtrav.client.commands.operator import clock_offset, status_table
from gcdtrav.schemas.config import Method
from gcdtrav.schemas.messages import ServiceStatus, SourceStatus

ROS_TOPIC = "robot_42/sensors/camera/front_left/color/image_raw"  # longer than any fixed column


def a_status(instance: str, sources: dict[str, SourceStatus]) -> ServiceStatus:
    return ServiceStatus(
        instance=instance, uptime_s=12.0, model="CIDAS/clipseg-rd64-refined", anchor_set_version="624409ca726582b2",
        method=Method.GCD, precision="ort-int8-vit", queued=0, sources=sources, rejected_by_reason={}, last_errors=[],
    )  # fmt: skip


def columns(line: str) -> list[tuple[int, int]]:
    """(start, end) of every field of a line, fields being separated by two spaces or more."""
    return [match.span() for match in re.finditer(r"\S+(?: \S+)*", line)]


def test_every_source_in_full_under_aligned_headers_with_reasons_and_why() -> None:
    served = SourceStatus(
        received=10, processed=8, dropped=2, dropped_by_reason={"replaced": 2}, latency_ms={"p50": 80.0, "p99": 120.0}
    )
    stale = SourceStatus(
        received=3, dropped=3, stale=3, dropped_by_reason={"stale": 3}, refused=True,
        problem="stale: captured 3600.0 s ago, over max_frame_age_s = 5 s",
    )  # fmt: skip
    broken = SourceStatus(received=6, rejected=6, rejected_by_reason={"undecodable": 6}, problem="undecodable: x")
    statuses = [
        a_status("a-rather-long-instance-name", {ROS_TOPIC: served, "r9/stale": stale}),
        a_status("b", {"png": broken}),
    ]
    lines = status_table(statuses).splitlines()

    instance_header, *instance_rows = lines[: lines.index("")]
    for row in instance_rows:  # right-aligned numbers end under their headers' ends, the model column's start
        ends, header_ends = [end for _, end in columns(row)], [end for _, end in columns(instance_header)]
        assert ends[1] == header_ends[1] and ends[3:] == header_ends[3:]
        assert columns(row)[2][0] == columns(instance_header)[2][0]
    header = next(line for line in lines if line.startswith("source "))
    rows = [line for line in lines if line.startswith((ROS_TOPIC, "r9/stale", "png "))]
    assert [row.split()[0] for row in rows] == ["r9/stale", ROS_TOPIC, "png"]  # never cut
    spans = columns(header)
    for row in rows:
        fields = columns(row)
        assert fields[1][0] == spans[1][0]  # instance: left-aligned, starts under its header
        assert [end for _, end in fields[2:10]] == [end for _, end in spans[2:10]]  # numbers: right-aligned
    assert "stale 3 (not tracked: every frame refused)" in rows[0]
    assert "replaced 2" in rows[1] and "undecodable 6" in rows[2]
    why = "  r9/stale (a-rather-long-instance-name): stale: captured 3600.0 s ago, over max_frame_age_s = 5 s"
    assert why in lines
    assert "  png (b): undecodable: x" in lines


def test_history_names_the_start_set_instead_of_1970() -> None:
    from gcdtrav.client.commands.operator import history_lines
    from gcdtrav.schemas.anchors import default_anchor_set
    from gcdtrav.schemas.messages import AnchorHistoryEntry, AnchorHistoryReply

    paper = default_anchor_set()
    entries = [
        AnchorHistoryEntry(accepted_at=1_795_000_000.0, version=paper.version, anchor_set=paper),
        AnchorHistoryEntry(accepted_at=0.0, version=paper.version, anchor_set=paper),  # the set it started with
    ]
    lines = history_lines([AnchorHistoryReply(instance="box-1", entries=entries)])
    assert lines[0] == "instance box-1:" and "1970" not in "\n".join(lines)
    assert lines[2].startswith("   rollback 1  start set           ") and lines[1].split()[1].startswith("2026-")
    assert lines[1].index(paper.version) == lines[2].index(paper.version)  # columns still aligned


def test_each_source_shows_its_clock_offset_and_clocks_off_by_a_second_are_named() -> None:
    sources = {
        "behind/front": SourceStatus(clock_offset_s=3600.021),
        "synced/front": SourceStatus(clock_offset_s=0.012),
        "bare/cam": SourceStatus(),
        "bag/cam": SourceStatus(clock_offset_s=1.1e8),
    }
    lines = status_table([a_status("box-1", sources)]).splitlines()
    header = next(line for line in lines if line.startswith("source "))
    clock = columns(header)[10]  # after unchanged (issue 34)
    assert header[clock[0] : clock[1]] == "clock s"
    rows = [line for line in lines if line.split()[:1] and line.split()[0] in sources]
    shown = {row.split()[0]: row[: clock[1]].split()[-1] for row in rows}  # right-aligned under its header
    assert shown["behind/front"] == "+3600.02" and shown["synced/front"] == "+0.01"
    assert shown["bare/cam"] == "-" and shown["bag/cam"] == "+1.1e+08"
    warning = next(line for line in lines if line.startswith("clocks off"))
    assert "bag/cam, behind/front (" in warning and "synced/front" not in warning


def test_offsets_at_their_edges() -> None:
    assert clock_offset(None) == "-" and clock_offset(0.0) == "+0.00" and clock_offset(-3600.0) == "-3600.00"


def test_a_source_refused_for_an_undecodable_frame_is_not_called_a_capacity_problem() -> None:
    from gcdtrav.client.commands.operator import reasons
    from gcdtrav.schemas.messages import SourceStatus

    junk = SourceStatus(received=1, rejected=1, rejected_by_reason={"undecodable": 1}, refused=True)
    assert reasons(junk) == "undecodable 1 (not tracked: every frame refused)"
    full = SourceStatus(received=2, rejected=2, rejected_by_reason={"too_many_sources": 2}, refused=True)
    assert reasons(full) == "too_many_sources 2 (not tracked: no source slot left)"
