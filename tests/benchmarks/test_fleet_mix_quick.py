"""benchmarks/fleet_mix.py --quick: the mixed fleet's two phases on a tiny model, for correctness only. Nothing
is compared across the phases: alone, the tiny model keeps up with every robot, but on a loaded machine round
robin falls behind and both phases infer as fast as the machine lets them (a full run beside two other suites
counted 341 inferences for need, 308 for round robin). The lead times the real run."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("torch")

ROOT = Path(__file__).resolve().parents[2]


def test_quick_fleet_mix_reuses_parked_views_and_maps_their_changes(tmp_path: Path) -> None:
    out = tmp_path / "mix.json"
    command = [sys.executable, "-m", "benchmarks.fleet_mix", "--quick", "--seconds", "5", "--out", str(out)]
    result = subprocess.run(command, capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert result.returncode == 0, result.stderr[-3000:]
    report = json.loads(out.read_text())
    assert report["cpu"] and {p["phase"] for p in report["phases"]} == {"round_robin", "need"}
    phases = {p["phase"]: {r["robot"]: r for r in p["robots"]} for p in report["phases"]}
    for name, rr in phases["round_robin"].items():
        need = phases["need"][name]
        assert rr["service"]["unchanged"] == 0 and rr["inferred_maps_per_s"] > 0, result.stdout
        assert need["maps_per_s"] > 0, result.stdout
        if rr["kind"] == "parked":  # answered at their rate, inferred far less
            assert need["service"]["unchanged"] > need["service"]["processed"], result.stdout
            assert need["change_to_map_s"] and None not in need["change_to_map_s"], result.stdout
        else:  # panning: inferred (a slow pan's frame may be reused while it is within the noise of the last)
            assert need["service"]["processed"] > need["service"]["unchanged"], result.stdout
    summary = report["summary"]
    assert summary["change_to_map_s"]["without_new_map"] == 0, result.stdout
