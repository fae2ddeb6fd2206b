"""benchmarks/experience.py --quick: the zenoh-free path from commands and odometry to a fitted proposal runs
and moves the anchors the right way (the goals need the full drive: benchmarks/README.md, Experience)."""

from __future__ import annotations

from benchmarks.experience import run, table


def test_a_short_drive_pairs_outcomes_and_moves_grass_and_sand_toward_the_truth() -> None:
    result = run(drive_s=120.0, after_s=60.0, seed=0)
    counts = result["counts"]
    assert counts["pairs"] > 1000 and not any(name.startswith("rejected") for name in counts)
    fitted = {a["concept"]: a for a in result["anchors"]}
    assert fitted["sand"]["fitted"] < 0.3 and fitted["sand"]["pairs"] > 100  # start 0.4, truth 0.15
    assert fitted["grass"]["fitted"] > 0.65  # start 0.5, truth 0.8
    assert fitted["water"]["fitted"] == 0.02  # never seen on this short drive: it stays
    assert result["held_out_after"]["mae"] < result["held_out_before"]["mae"]
    assert result["second_drive_pairs"] > 0
    assert "| sand | 0.40 | 0.15 |" in table(result)
