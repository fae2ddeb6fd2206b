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


def test_after_a_link_loss_only_the_robots_own_safe_mask_slows_it(capsys) -> None:  # type: ignore[no-untyped-def]
    """--link-loss --quick: the service's safe mask never crosses a dead link (the same drive as none); the
    relay's guard slows the robot to the floor after_s after the last mask, on hazards and on clear ground."""
    from benchmarks.speed import SAFE_AFTER_S, link_loss_table, run_link_loss

    drives = {d.layer: d for d in run_link_loss(1, 1, QUICK_ROUTE_M)}
    for ground in ("hazards", "clear"):
        none, service, robot = (drives[f"{ground}, safe mask: {guard}"] for guard in ("none", "service", "robot"))
        assert none.loss_at_s == service.loss_at_s == robot.loss_at_s is not None
        assert none.time_to_goal_s == service.time_to_goal_s and none.fast_after_loss_m == service.fast_after_loss_m
        assert robot.reached and robot.time_to_goal_s > none.time_to_goal_s  # the price: the floor to the goal
        # above the floor's speed only until the guard acts: at most after_s (plus a mask period) at full speed
        assert robot.fast_after_loss_m <= V_MAX * (SAFE_AFTER_S + 1.0) < none.fast_after_loss_m
    assert main(["--link-loss", "--quick"]) == 0
    assert "| clear, safe mask: robot | 1 (1) |" in capsys.readouterr().out
    assert "hazard contacts" in link_loss_table(list(drives.values()))
