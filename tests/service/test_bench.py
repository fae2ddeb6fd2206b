"""`gcdtrav bench` and the project's benchmark (benchmarks/bench.py: the same plus the service rows) end to end
on a tiny model: every group produces rows and the JSON says what it measured.

Timings themselves are not asserted (they belong to the benchmark's output, not to tests).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

pytest.importorskip("torch")


def test_bench_runs_every_group_and_writes_json(tiny_model_dir: Path, tmp_path: Path) -> None:
    from benchmarks import bench

    out = tmp_path / "bench.json"
    argv = ["--model", str(tiny_model_dir), "--runs", "1", "--naive-runs", "1", "--zenoh-frames", "2"]
    argv += ["--robots", "1,2", "--robot-fps", "5", "--robot-seconds", "1", "--skip", "engine", "--out", str(out)]
    assert bench.main(argv) == 0
    summary = json.loads(out.read_text("utf-8"))
    rows = summary["rows"]
    assert {"mode", "attention", "anchors", "input", "zenoh", "robots"} <= {row["group"] for row in rows}
    assert [row["name"] for row in rows if row["group"] == "anchors"][:4] == [
        f"{n} anchors ({summary['default_precision']})" for n in (2, 13, 32, 64)
    ]
    assert all(row["median_ms"] > 0 and math.isfinite(row["p95_ms"]) for row in rows)

    from gcdtrav.service.backends.clipseg import available_precisions

    assert set(summary["parity"]) == set(available_precisions()) - {"fp32"}  # every mode this machine runs
    assert summary["default_precision"] in available_precisions()
    assert summary["machine"]["cpu"] and "cpu_features" in summary["machine"]
    for report in summary["parity"].values():
        assert {"max_dT", "p99_dT", "max_dU", "p99_dU", "top_anchor_changed", "activation_cosine_min"} <= set(report)
    assert "trained model" in summary["parity_method"]

    robots = [row for row in rows if row["group"] == "robots"]
    assert [row["extra"]["robots"] for row in robots] == [1, 2]
    for row in robots:  # a tiny model keeps up with 5 fps per robot: every robot gets maps in the window
        assert row["peak_rss_mb"] > 50  # the service process's own memory, model included
        assert row["extra"]["maps_per_robot_min"] > 0 and row["fps"] == pytest.approx(
            row["extra"]["maps_per_s"], abs=0.01
        )
    zenoh_row = next(row for row in rows if row["group"] == "zenoh")
    assert zenoh_row["runs"] == 2 and "overhead_median_ms" in zenoh_row["extra"]


def test_shipped_bench_times_the_given_checkpoint_without_service_rows(tiny_model_dir: Path, tmp_path: Path) -> None:
    from gcdtrav.service.commands import bench

    out = tmp_path / "bench.json"
    argv = ["--model", str(tiny_model_dir), "--runs", "1", "--naive-runs", "1", "--modes", "int8"]
    assert bench.main([*argv, "--skip", "sweeps,engine", "--out", str(out)]) == 0
    rows = json.loads(out.read_text("utf-8"))["rows"]
    assert {row["name"] for row in rows if row["group"] == "mode"} >= {"fast path fp32", "fast path int8"}
    assert not {"zenoh", "robots"} & {row["group"] for row in rows}  # those need the repository's tools/
    with pytest.raises(SystemExit):  # the service options belong to benchmarks/bench.py
        bench.main([*argv, "--robots", "1"])


def test_bench_breaks_a_frame_into_stages_and_names_the_floor(tiny_model_dir: Path, tmp_path: Path) -> None:
    from gcdtrav.service.commands import bench

    out = tmp_path / "bench.json"
    argv = ["--model", str(tiny_model_dir), "--runs", "2", "--naive-runs", "1", "--modes", "int8"]
    assert bench.main([*argv, "--skip", "sweeps,engine", "--out", str(out)]) == 0
    summary = json.loads(out.read_text("utf-8"))
    precision = summary["default_precision"]
    stages = [row for row in summary["rows"] if row["group"] == "stage"]
    assert [row["name"] for row in stages] == [
        f"{stage} ({precision})"
        for stage in (
            "preprocessing",
            "vision transformer",
            "decoder and upsampling",
            "GCD engine (T and U)",
            "encoding T and U (PNG)",
        )
    ]
    shares = [float(row["note"].split(" %")[0]) for row in stages]
    assert sum(shares) == pytest.approx(100, abs=len(shares))  # each rounded to a whole per cent
    (floor,) = [row for row in summary["rows"] if row["group"] == "floor"]
    assert floor["name"].startswith("floor: the frame's products in ") and floor["median_ms"] > 0
    parts = {row["name"].split(" in ")[0]: row["median_ms"] for row in summary["rows"] if row["group"] == "floor part"}
    assert list(parts) == ["floor: vision transformer", "floor: decoder and upsampling"]  # the stages with products
    assert sum(parts.values()) == pytest.approx(floor["median_ms"], abs=0.02)  # each row rounded to 0.01 ms
    stage_ms = {row["name"].removesuffix(f" ({precision})"): row["median_ms"] for row in stages}
    for row in (row for row in summary["rows"] if row["group"] == "floor part"):
        took, part = stage_ms[row["name"].removeprefix("floor: ").split(" in ")[0]], row["median_ms"]
        multiple = float(row["note"].removeprefix("the stage took ").removesuffix("x this"))
        # the rows hold medians rounded to 0.01 ms, the note the multiple of the unrounded ones to 0.01
        assert (took - 0.005) / (part + 0.005) - 0.005 <= multiple <= (took + 0.005) / max(part - 0.005, 1e-9) + 0.005
    assert min(parts.values()) > 0
    (peak,) = [row for row in summary["rows"] if row["group"] == "floor peak"]
    assert 0 < peak["median_ms"] <= floor["median_ms"] + 0.01  # every product at the best rate: the lowest
    fast = next(row for row in summary["rows"] if row["name"] == f"fast path {precision}")
    assert summary["default_vs_floor"] == pytest.approx(fast["median_ms"] / floor["median_ms"], rel=0.01)
    assert summary["default_vs_peak_floor"] == pytest.approx(fast["median_ms"] / peak["median_ms"], rel=0.01)


def test_the_table_keeps_its_columns_for_long_groups_and_names() -> None:
    from gcdtrav.service.commands.bench import format_table, make_row

    rows = [
        make_row("fast path int8", "mode", [10.0], 100.0),
        make_row("floor: decoder and upsampling in int8, a long name", "floor part", [1.5], 0.0, "a note"),
    ]
    lines = format_table(rows).splitlines()
    bars = [[i for i, char in enumerate(line) if char == "|"] for line in (lines[0], *lines[2:])]
    assert len({tuple(positions[:7]) for positions in bars}) == 1  # every row's columns where the header's are
    assert "floor part" in lines[3] and lines[3].endswith("| a note")
