"""benchmarks/speed.py --quick: the closed loop runs end to end (frames, fusion, the mask's CDR, Nav2's
SpeedFilter at the robot's pose) and the layer slows the robot on ambiguous ground only; the full table is in
benchmarks/README.md ("Speed from uncertainty")."""

from __future__ import annotations

from benchmarks.speed import FLOOR, LAYERS, QUICK_ROUTE_M, V_MAX, V_SAFE, main, run, summary


def test_a_short_route_with_the_layer_is_slow_on_ambiguous_ground_only_and_touches_no_hazard(capsys) -> None:  # type: ignore[no-untyped-def]
    off, on = run(1, 1, QUICK_ROUTE_M, (LAYERS[1],))
    assert off.layer == "off" and on.layer == LAYERS[1].name and off.hazards == on.hazards >= 1
    assert off.reached and on.reached and off.stalls == on.stalls == 0
    assert off.contacts == off.hazards  # at full speed over every hazard on the route
    assert on.contacts == 0 and max(on.entry_speeds) <= V_SAFE and min(off.entry_speeds) == V_MAX
    assert off.mean_speed_ambiguous == V_MAX and on.mean_speed_ambiguous <= V_SAFE
    assert on.mean_speed_ambiguous >= FLOOR * V_MAX - 1e-9  # never below the floor: no stall
    # clear ground is slowed only lead_m before and after ambiguous ground (and at the start, unknown: the floor)
    assert on.mean_speed_clear > on.mean_speed_ambiguous + 0.2
    assert on.time_to_goal_s > off.time_to_goal_s  # the cost, in time
    rows = summary([off, on])
    assert [row["layer"] for row in rows] == ["off", LAYERS[1].name]
    assert main(["--quick"]) == 0
    assert "| off | 1 (1) |" in capsys.readouterr().out
