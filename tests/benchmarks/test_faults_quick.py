"""benchmarks/faults.py --quick: SIGKILL, a hung worker and a flood of new names on 2 instances, on loopback.

The goals it checks (issue 26), with the looser bounds this shared CI box needs:
- no map arrives older than max_frame_age_s (exact);
- a SIGKILLed instance's robots are blind at most 3 s beyond their frame time (exact goal: the TCP link
  closes, fail-over is immediate);
- a hung instance's robots: at most stall_after_s (2.5 s) + 3 s, room for this shared box; benchmarks/README.md,
  Faults, reports the measured value;
- every live instance ends on the same anchor version;
- a new robot during a 1000 names/s flood gets a map: within 2 s here (the goal, one frame time, is in the table).

Maps out of order at a consumer that does not filter are reported, not asserted: at a hand-over two instances
own a source for as long as their views of the fleet differ (longer on a loaded host), and the client holds
back the older map (tests/client/test_maps_order.py); benchmarks/README.md, Faults, counts them per fault.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("torch")

ROOT = Path(__file__).resolve().parents[2]
STALL_AFTER_S = 2.5  # the setting's default


def test_quick_faults_keep_robots_served_fresh_and_anchor_versions_agree(tmp_path: Path) -> None:
    out = tmp_path / "faults.json"
    command = [sys.executable, "-m", "benchmarks.faults", "--quick", "--out", str(out)]
    # about 90 s on a quiet 2-core box, 7 minutes measured with 8 other test jobs on it: the limit only bounds a hang
    result = subprocess.run(command, capture_output=True, text=True, timeout=900, cwd=ROOT)
    assert result.returncode == 0, result.stderr[-3000:]
    results = {r["fault"]: r for r in json.loads(out.read_text())["results"]}
    assert set(results) == {"sigkill", "hang", "flood"}, result.stdout
    for fault, r in results.items():
        assert r["stale_maps"] == 0, (fault, result.stdout)
        assert r["goals"]["same_anchor_version"], (fault, result.stdout)
    assert results["sigkill"]["blind_max_s"] <= 3.0, result.stdout
    assert results["hang"]["blind_max_s"] <= STALL_AFTER_S + 3.0, result.stdout
    assert results["hang"]["blind_max_s"] > 1.0, result.stdout  # the hang did happen (not a no-op wrapper)
    first = results["flood"]["newcomer_first_map_s"]
    assert first is not None and first <= 2.0, result.stdout
    assert results["flood"]["flood_frames"] > 1000, result.stdout
