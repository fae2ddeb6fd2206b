"""Velocity-tracking outcomes from commands and odometry, in ROS CDR and in msgpack or JSON."""

from __future__ import annotations

import json

import numpy as np
import pytest
from gcdtrav.schemas.experience import Odometry2D, Twist2D
from gcdtrav.schemas.messages import MessageError
from gcdtrav.schemas.outcomes import VelocityTracker, decode_command, decode_odometry
from gcdtrav.schemas.settings import ExperienceSettings
from gcdtrav.service.experience.service import is_ros_topic
from gcdtrav.service.experience.snapshots import SnapshotRing
from gcdtrav.service.grid.fusion import GridSpec, GroundGrid

from tools.ros_fixtures import odometry_cdr, twist_cdr

SETTINGS = ExperienceSettings(footprint_m=0.6, min_command_mps=0.1, outcome_spacing_m=0.3, outcome_period_s=2.0)


def drive(tracker: VelocityTracker, command: float, speed: float, steps: int, start: float = 0.0) -> list:
    outcomes = []
    for k in range(steps):
        t = start + 0.05 * k
        if k % 2 == 0:
            tracker.on_command(Twist2D(vx=command), received_at=1000.0 + t)  # the service's clock
        odometry = Odometry2D(stamp=t, x=speed * t, y=0.0, vx=speed)  # the robot's clock: 1000 s behind
        found = tracker.on_odometry(odometry, received_at=1000.0 + t)
        if found is not None:
            outcomes.append(found)
    return outcomes


def test_the_score_is_achieved_over_commanded_speed_spaced_by_distance() -> None:
    outcomes = drive(VelocityTracker(SETTINGS), command=1.0, speed=0.5, steps=100)  # 5 s at 0.5 m/s: 2.5 m
    assert len(outcomes) == pytest.approx(2.5 / 0.3, abs=1)
    assert all(o.score == pytest.approx(0.5) and o.kind == "velocity" and o.radius_m == 0.3 for o in outcomes)
    assert all(0 < o.x < 2.5 for o in outcomes)
    assert np.all(np.diff([o.x for o in outcomes]) > 0.25)


def test_faster_than_commanded_is_clipped_to_one_and_a_stall_still_reports() -> None:
    assert {o.score for o in drive(VelocityTracker(SETTINGS), 0.5, 0.9, 60)} == {1.0}
    stalled = drive(VelocityTracker(SETTINGS), 1.0, 0.0, 100)  # no distance: one outcome per outcome_period_s
    assert len(stalled) == 2 and {o.score for o in stalled} == {0.0}


def test_no_outcome_below_min_command_or_with_a_stale_command() -> None:
    assert drive(VelocityTracker(SETTINGS), command=0.05, speed=0.0, steps=100) == []  # told to (almost) stop
    tracker = VelocityTracker(SETTINGS)
    tracker.on_command(Twist2D(vx=1.0), received_at=0.0)
    for k in range(100):  # the command is 0.5 s old after 10 samples: no longer in force
        assert tracker.on_odometry(Odometry2D(stamp=k, x=0.0, y=0.0, vx=0.0), received_at=1.0 + k) is None
    assert tracker.counts["not_commanded"] == 100


def test_a_command_recorded_after_the_samples_receipt_is_in_force() -> None:
    """zenoh runs each subscriber's callback on its own thread: the next command can be recorded between an
    odometry sample's receipt and its grading. Loaded, that reset every window and no outcome came."""
    tracker, outcomes = VelocityTracker(SETTINGS), []
    for k in range(40):  # 0.5 m/s commanded 1 m/s; each command lands 1 ms after the sample's receipt
        tracker.on_command(Twist2D(vx=1.0), received_at=100.0 + 0.05 * k + 0.001)
        outcomes.append(tracker.on_odometry(Odometry2D(stamp=0.05 * k, x=0.025 * k, y=0.0, vx=0.5), 100.0 + 0.05 * k))
    assert "not_commanded" not in tracker.counts
    assert [o.score for o in outcomes if o is not None] == pytest.approx([0.5] * 3)


def test_ros_cdr_and_zenoh_forms_decode_alike() -> None:
    assert is_ros_topic("/cmd_vel") and not is_ros_topic("robot/cmd_vel")
    from_ros = decode_command(twist_cdr(0.8, 0.1, 0.3))
    assert (from_ros.vx, from_ros.vy, from_ros.wz) == pytest.approx((0.8, 0.1, 0.3))
    assert decode_command(Twist2D(vx=0.8).pack()).vx == 0.8
    assert decode_command(json.dumps({"vx": 0.8, "future": 1}).encode()).vx == 0.8
    odometry = decode_odometry(odometry_cdr(1.7e9 + 0.25, 1.0, 2.0, 0.5, 0.7))
    assert (odometry.stamp, odometry.x, odometry.y, odometry.yaw, odometry.vx) == pytest.approx(
        (1.7e9 + 0.25, 1.0, 2.0, 0.5, 0.7)
    )
    assert decode_odometry(json.dumps({"stamp": 1.0, "x": 1, "y": 2, "vx": 0.5}).encode()).vx == 0.5


@pytest.mark.parametrize(
    ("payload", "decoder"),
    [
        (b"\x00\x01\x00\x00\x01", decode_command),  # truncated CDR
        (twist_cdr(0.5)[:-8], decode_odometry),
        (b'{"vx": NaN}', decode_command),
        (b'{"vx": "fast"}', decode_command),
        (b"{not json", decode_command),
        (json.dumps({"stamp": 1.0, "x": 1e9, "y": 0, "vx": 0}).encode(), decode_odometry),
        (b"x" * 70_000, decode_odometry),
    ],
)
def test_bad_inputs_are_message_errors(payload: bytes, decoder: object) -> None:
    with pytest.raises(MessageError):
        decoder(payload)  # type: ignore[operator]


def test_the_snapshot_ring_stays_within_its_budget_and_restarts_on_a_replayed_bag() -> None:
    grid = GroundGrid(GridSpec(size_m=4.0, resolution_m=0.1), 2)
    points = np.random.default_rng(0).uniform(-2, 2, (2000, 2))
    weights = np.full((2, 2000), 0.5, np.float32)
    from gcdtrav.schemas.anchors import Anchor, AnchorSet

    anchors = AnchorSet(anchors=[Anchor(concept="mud", position=0.1), Anchor(concept="grass", position=0.5)])
    grid.add(points, weights, 0.0, anchors)
    one = SnapshotRing(0.25, 10**9, 60.0)
    one.capture(grid)
    budget = 3 * one.nbytes
    ring = SnapshotRing(every_s=0.25, budget_bytes=budget, keep_s=60.0)
    for k in range(40):
        grid.add(points, weights, k * 0.1, anchors)
        ring.capture(grid)
        assert ring.nbytes <= budget
    assert len(ring) == 3  # one every 0.3 s (frames every 0.1 s): only the newest three fit
    assert ring.before(3.5) is not None and ring.before(3.2) is None  # 3.3, 3.6, 3.9 kept
    grid.add(points, weights, 100.0, anchors)
    ring.capture(grid)
    grid.stamp = 1.0  # a bag replayed from its start
    ring.capture(grid)
    assert len(ring) == 1 and ring.before(5.0) is not None
