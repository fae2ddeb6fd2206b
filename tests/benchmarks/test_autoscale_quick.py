"""benchmarks/autoscale.py --quick: a real Prometheus, a controller with the HPA formula, robots 2 -> 6 -> 2.

What it checks (issue 43), loosely enough for a shared CI box: the fleet scales up when robots come, no map
arrives older than max_frame_age_s, and an instance removed by SIGTERM leaves no robot more than 2 s without
maps. benchmarks/README.md, Autoscaling, reports the full run.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("torch")
pytestmark = pytest.mark.skipif(shutil.which("prometheus") is None, reason="no prometheus binary (.ci/run installs it)")

ROOT = Path(__file__).resolve().parents[2]


def test_quick_autoscale_scales_up_without_stale_maps_and_drains_unfelt(tmp_path: Path) -> None:
    out = tmp_path / "autoscale.json"
    command = [sys.executable, "-m", "benchmarks.autoscale", "--quick", "--out", str(out)]
    result = subprocess.run(command, capture_output=True, text=True, timeout=400, cwd=ROOT)
    assert result.returncode == 0, result.stderr[-3000:]
    phases = json.loads(out.read_text())["phases"]
    assert [p["robots"] for p in phases] == [2, 6, 2]
    assert all(p["stale_maps"] == 0 and p["maps"] > 0 for p in phases), result.stdout
    assert any(e["kind"] == "up" for e in phases[1]["scale_events"]), result.stdout  # 6 robots need more
    downs = [e for p in phases for e in p["scale_events"] if e["kind"] == "down"]
    assert all(e["longest_gap_s"] <= 2.0 for e in downs), result.stdout
