"""The churn soak, short: every churn frame under a new source name, beside steady robots, on loopback.

benchmarks/soak.py --churn runs for 10 minutes on the real architecture (benchmarks/README.md); this is
its 45-second version on the tiny model, with a small source cap and idle time so that both bounds act.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("torch")

ROOT = Path(__file__).resolve().parents[3]
MAX_SOURCES = 8


def test_churning_sources_stay_capped_are_forgotten_and_steady_robots_are_served_evenly(
    tiny_model_dir: Path, tmp_path: Path
) -> None:
    out = tmp_path / "churn.json"
    command = [sys.executable, "-m", "benchmarks.soak", "--model", str(tiny_model_dir)]  # from the checkout
    command += ["--minutes", "0.75", "--robots", "2", "--fps", "5", "--instances", "1", "--churn", "5"]
    command += ["--max-sources", str(MAX_SOURCES), "--source-idle-s", "3", "--sample-seconds", "5"]
    command += ["--history-budget-mb", "4", "--out", str(out)]
    result = subprocess.run(command, capture_output=True, text=True, timeout=240, cwd=ROOT)
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads(out.read_text())
    churn = report["churn"]
    summary = json.dumps({k: v for k, v in churn.items() if k != "rss"} | {"errors": report["errors"]})
    samples = churn["bounds"]["soak-0"]
    assert len(samples) >= 4, summary  # status queries answered while the service was loaded
    assert all(0 < s["tracked_sources"] <= MAX_SOURCES for s in samples), summary
    assert all(s["history_mb"] <= 4 for s in samples), summary
    refused = churn["churn_frames_refused_too_many_sources"]
    assert refused > 0, summary  # the cap acted ...
    assert churn["churn_frames_sent"] - refused > 2 * MAX_SOURCES, summary  # ... forgotten sources made room
    # The steady robots are served evenly: each gets maps, and the same share of the frames it sent in (the
    # scheduler's doing), not the same count over wall time (a slow or busy host's doing as well).
    assert churn["steady_maps_min_max"][0] > 0, summary
    low, high = churn["steady_served_min_max"]
    assert high - low <= 0.25 * high, summary
    assert report["lost"] == 0 and set(report["errors"]["soak-0"]) <= {"too_many_sources", "candidate_evicted"}, summary
