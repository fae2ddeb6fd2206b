"""Outcomes measured on the robot (client/relay/outcomes.py): the service's own rules (one tracker in
schemas/outcomes.py), batched at most every batch_period_s, a contact per press, the planned path shortened and
sent when it changes; the robot's inputs decoded as CDR (checked against ROS 2's serialiser) or msgpack/JSON."""

from __future__ import annotations

import math
from typing import Any

import pytest
from gcdtrav.client.relay.outcomes import OutcomeLink, follows, robot_key, shortened
from gcdtrav.schemas.experience import (
    MAX_BATCH_OUTCOMES,
    Odometry2D,
    OutcomeBatch,
    PlannedPath,
    TraversalOutcome,
    Twist2D,
)
from gcdtrav.schemas.messages import MessageError
from gcdtrav.schemas.outcomes import VelocityTracker, decode_command, decode_contact, decode_odometry
from gcdtrav.schemas.relay import RelayOutcomes
from gcdtrav.schemas.ros_nav import RosNavError
from gcdtrav.schemas.settings import ExperienceSettings

SETTINGS = RelayOutcomes(batch_period_s=1.0)


class Publisher:
    def __init__(self) -> None:
        self.payloads: list[bytes] = []
        self.heard = True  # someone across the link subscribes

    def put(self, payload: bytes) -> None:
        self.payloads.append(payload)

    def matching(self) -> bool:
        return self.heard


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def link() -> tuple[OutcomeLink, Publisher, Publisher, Clock]:
    outcomes, paths, clock = Publisher(), Publisher(), Clock()
    return OutcomeLink(SETTINGS, "r1/front", outcomes, paths, clock), outcomes, paths, clock


def send_at(relay: OutcomeLink, clock: Clock, now: float) -> float:
    clock.now = now
    return relay.send_due()


def drive(target: Any, command: float, speed: float, steps: int, start: float = 100.0) -> None:
    """A robot told ``command`` m/s doing ``speed`` along x, 20 Hz odometry."""
    for step in range(steps):
        target.on_command(Twist2D(vx=command))
        stamp = start + step * 0.05
        target.on_odometry(Odometry2D(stamp=stamp, x=speed * step * 0.05, y=0.0, vx=speed))


def test_the_relay_grades_by_the_services_rules_and_sends_a_batch_per_period() -> None:
    relay, outcomes, _, clock = link()
    drive(relay, command=1.0, speed=0.5, steps=100)  # 5 s at half the commanded speed: 2.5 m
    assert send_at(relay, clock, 10.0) == 11.0 and len(outcomes.payloads) == 1
    batch = OutcomeBatch.unpack(outcomes.payloads[0])
    # the service's own tracker, on the service's settings with the same numbers, makes the same outcomes
    service = VelocityTracker(ExperienceSettings(enabled=False))
    expected = []
    for step in range(100):
        service.on_command(Twist2D(vx=1.0), step * 0.05)
        made = service.on_odometry(
            Odometry2D(stamp=100.0 + step * 0.05, x=0.5 * step * 0.05, y=0.0, vx=0.5), step * 0.05
        )
        expected += [made] if made is not None else []
    assert batch.outcomes == expected and len(expected) >= 7
    assert {outcome.score for outcome in batch.outcomes} == {0.5} and batch.dropped == 0
    assert len(outcomes.payloads[0]) < 120 * len(batch.outcomes)  # a few bytes an outcome
    drive(relay, command=1.0, speed=1.0, steps=20, start=106.0)
    assert send_at(relay, clock, 10.5) == 11.0 and len(outcomes.payloads) == 1  # within the period: waits
    send_at(relay, clock, 11.0)
    assert len(outcomes.payloads) == 2 and relay.batches == 2 and relay.sent == relay.measured
    send_at(relay, clock, 12.0)
    assert len(outcomes.payloads) == 2  # nothing measured: nothing sent


def test_a_contact_per_press_at_the_newest_pose_and_the_robots_own_outcomes() -> None:
    relay, outcomes, _, clock = link()
    relay.on_contact(True)  # before any pose: nowhere to put it
    assert relay.contacts.without_pose == 1
    relay.on_odometry(Odometry2D(stamp=5.0, x=2.0, y=-1.0, vx=0.0))
    relay.on_contact(False)
    relay.on_contact(True)
    relay.on_contact(True)  # held: the same press
    relay.on_outcome(TraversalOutcome(stamp=6.0, x=3.0, y=0.0, score=0.2, kind="contact"))
    send_at(relay, clock, 0.0)
    (payload,) = outcomes.payloads
    press, own = OutcomeBatch.unpack(payload).outcomes
    assert (press.kind, press.score, press.stamp, press.x, press.y) == ("contact", 0.0, 5.0, 2.0, -1.0)
    assert press.radius_m == SETTINGS.footprint_m / 2 and own.score == 0.2


def test_a_link_that_cannot_send_keeps_the_newest_and_says_how_many_it_dropped() -> None:
    relay, outcomes, _, clock = link()
    for index in range(MAX_BATCH_OUTCOMES + 5):
        relay.on_outcome(TraversalOutcome(stamp=float(index), x=0.0, y=0.0, score=1.0, kind="velocity"))
    send_at(relay, clock, 0.0)
    batch = OutcomeBatch.unpack(outcomes.payloads[0])
    assert len(batch.outcomes) == MAX_BATCH_OUTCOMES and batch.dropped == 5 and batch.outcomes[0].stamp == 5.0


def test_while_nobody_receives_the_outcomes_wait_and_leave_in_the_first_batch_after() -> None:
    """A put that no subscriber matches is lost (zenoh drops it at the writer) and was counted sent; now the
    outcomes wait while nobody across the link receives, the newest MAX_BATCH_OUTCOMES, the rest dropped."""
    relay, outcomes, paths, clock = link()

    def outcome(stamp: float) -> None:
        relay.on_outcome(TraversalOutcome(stamp=stamp, x=0.0, y=0.0, score=1.0, kind="velocity"))

    outcome(0.0)
    send_at(relay, clock, 0.0)
    assert len(outcomes.payloads) == 1 and not relay.holding
    outcomes.heard = paths.heard = False  # the service, its router or the link went away
    for second in range(1, 4):
        outcome(float(second))
        relay.on_path("odom", float(second), [(0.0, 0.0), (float(second), 0.0)])
        send_at(relay, clock, float(second))
    assert len(outcomes.payloads) == 1 and paths.payloads == [] and relay.holding
    assert relay.sent == 1 and relay.measured == 4
    for index in range(MAX_BATCH_OUTCOMES):  # a long outage: more than a batch holds
        outcome(10.0 + index)
    send_at(relay, clock, 4.0)
    outcomes.heard = paths.heard = True
    send_at(relay, clock, 5.0)
    held = OutcomeBatch.unpack(outcomes.payloads[1])
    assert len(held.outcomes) == MAX_BATCH_OUTCOMES and held.dropped == 3  # the oldest three gave way
    assert held.outcomes[0].stamp == 10.0 and relay.sent == 1 + MAX_BATCH_OUTCOMES and not relay.holding
    (path,) = paths.payloads
    assert PlannedPath.unpack(path).points == [(0.0, 0.0), (3.0, 0.0)]  # the newest path, once


def test_the_path_waits_for_its_own_receiver_and_the_outcomes_for_theirs() -> None:
    relay, outcomes, paths, clock = link()
    relay.on_outcome(TraversalOutcome(stamp=1.0, x=0.0, y=0.0, score=1.0, kind="velocity"))
    relay.on_path("odom", 1.0, [(0.0, 0.0), (2.0, 0.0)])
    outcomes.heard = False  # a planner's subscriber hears paths; nobody hears outcomes
    send_at(relay, clock, 0.0)
    assert outcomes.payloads == [] and len(paths.payloads) == 1 and relay.holding


def test_a_receiver_check_that_fails_holds() -> None:
    class Closing(Publisher):
        def matching(self) -> bool:
            raise RuntimeError("the session is closing")

    outcomes, paths, clock = Closing(), Publisher(), Clock()
    relay = OutcomeLink(SETTINGS, "r1/front", outcomes, paths, clock)
    relay.on_outcome(TraversalOutcome(stamp=1.0, x=0.0, y=0.0, score=1.0, kind="velocity"))
    send_at(relay, clock, 0.0)
    assert outcomes.payloads == [] and relay.holding and relay.sent == 0


def test_the_planned_path_is_sent_shortened_when_it_changes_and_renewed_before_the_service_forgets_it() -> None:
    relay, _, paths, clock = link()
    straight = [(0.1 * i, 0.0) for i in range(400)]  # 40 m, a vertex every 0.1 m
    relay.on_path("odom", 1.0, straight)
    send_at(relay, clock, 0.0)
    sent = PlannedPath.unpack(paths.payloads[0])
    assert sent.frame_id == "odom" and sent.points[0] == (0.0, 0.0)
    assert 19.9 <= sent.points[-1][0] <= 20.6
    assert all(b[0] - a[0] >= 0.5 - 1e-9 for a, b in zip(sent.points, sent.points[1:], strict=False))
    clock.now = 1.0  # the robot drove 3 m along it: the same plan, not sent again
    relay.on_path("odom", 2.0, straight[30:])
    send_at(relay, clock, 1.0)
    assert len(paths.payloads) == 1
    clock.now = SETTINGS.path_renew_s  # unchanged, but due: the service forgets a path after ask.path_timeout_s
    relay.on_path("odom", 3.0, straight[30:])
    send_at(relay, clock, SETTINGS.path_renew_s)
    assert len(paths.payloads) == 2
    relay.on_path("odom", 4.0, [(3.0, 0.0), (3.0, 5.0)])  # a new plan: a turn
    send_at(relay, clock, SETTINGS.path_renew_s + 1.0)
    assert len(paths.payloads) == 3 and PlannedPath.unpack(paths.payloads[2]).points[-1] == (3.0, 5.0)
    relay.on_path("odom", 5.0, [(3.0, 0.0), (3.3, 5.0)])  # the turn's end 0.3 m aside: the same plan
    send_at(relay, clock, SETTINGS.path_renew_s + 2.0)
    assert len(paths.payloads) == 3


def test_follows_at_its_edges() -> None:
    assert follows([], None, 10.0) and not follows([(0.0, 0.0)], None, 10.0) and not follows([], [(0.0, 0.0)], 10.0)
    assert follows([(0.2, 0.1)], [(0.0, 0.0)], 10.0) and not follows([(1.0, 0.0)], [(0.0, 0.0)], 10.0)
    line = [(0.0, 0.0), (10.0, 0.0)]
    assert follows([(2.0, 0.4), (9.0, -0.4)], line, 10.0) and not follows([(2.0, 0.6)], line, 10.0)
    assert follows([(2.0, 0.0), (8.0, 0.0), (30.0, 9.0)], line, 7.0)  # past the nearer part: not compared


@pytest.mark.parametrize(("length", "last"), [(0.1, (0.6, 0.0)), (1.0, (1.2, 0.0)), (100.0, (3.6, 0.0))])
def test_shortened_at_its_edges(length: float, last: tuple[float, float]) -> None:
    points = [(round(0.3 * i, 6), 0.0) for i in range(14)]  # every 0.3 m: every other kept (0.5 m apart at least)
    kept = shortened(points, length)
    assert kept[0] == (0.0, 0.0) and kept[-1] == pytest.approx(last)
    assert shortened([], 5.0) == [] and shortened([(1.0, 1.0)], 5.0) == [(1.0, 1.0)]


def test_inputs_as_ros_2_serialises_them_and_as_msgpack_or_json() -> None:
    from real_components import require_rclpy

    require_rclpy()
    from geometry_msgs.msg import Twist, TwistStamped
    from nav_msgs.msg import Odometry
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Bool

    twist = Twist()
    twist.linear.x, twist.linear.y, twist.angular.z = 0.8, -0.1, 0.3
    assert decode_command(serialize_message(twist), stamped=False) == Twist2D(vx=0.8, vy=-0.1, wz=0.3)
    stamped = TwistStamped()
    stamped.header.frame_id, stamped.twist = "base_link", twist
    assert decode_command(serialize_message(stamped), stamped=True) == Twist2D(vx=0.8, vy=-0.1, wz=0.3)
    odometry = Odometry()
    odometry.header.stamp.sec, odometry.header.frame_id = 12, "odom"
    odometry.pose.pose.position.x, odometry.pose.pose.orientation.z = 4.0, math.sin(0.25)
    odometry.pose.pose.orientation.w = math.cos(0.25)
    odometry.pose.covariance[35] = 7.0
    odometry.twist.twist.linear.x, odometry.twist.twist.angular.z = 1.25, -0.5
    decoded = decode_odometry(serialize_message(odometry))
    assert (decoded.stamp, decoded.frame_id, decoded.x, decoded.vx, decoded.wz) == (12.0, "odom", 4.0, 1.25, -0.5)
    assert decoded.yaw == pytest.approx(0.5)
    assert decode_contact(serialize_message(Bool(data=True))) and not decode_contact(
        serialize_message(Bool(data=False))
    )


def test_plain_inputs_and_what_is_refused() -> None:
    assert decode_command(Twist2D(vx=1.0).pack(), stamped=False).vx == 1.0
    assert decode_command(b'{"vx": 0.5}', stamped=False).vx == 0.5
    assert decode_odometry(Odometry2D(stamp=1.0, x=1.0, y=2.0, vx=0.3).pack()).vx == 0.3
    assert decode_contact(b" true\n") and not decode_contact(b"false")
    for bad in (b"maybe", b"\x00\x01\x00\x00\x07", b"\x00\x01"):
        with pytest.raises(RosNavError):
            decode_contact(bad)
    with pytest.raises(RosNavError):
        decode_command(b"\x00\x01\x00\x00" + b"\x00" * 8, stamped=False)  # truncated
    with pytest.raises(MessageError):
        decode_command(b'{"vx": "fast"}', stamped=False)
    with pytest.raises((MessageError, RosNavError)):
        decode_odometry(b"\x00\x01\x00\x00" + b"\xff" * 4)


@pytest.mark.parametrize(
    ("name", "kind", "key"),
    [
        ("robot/cmd_vel", "cmd_vel", "robot/cmd_vel"),
        ("/cmd_vel", "cmd_vel", "*/cmd_vel/geometry_msgs::msg::dds_::Twist_/*"),
        ("/r1/odom", "odometry", "*/r1/odom/nav_msgs::msg::dds_::Odometry_/*"),
        ("/bumper", "contact", "*/bumper/std_msgs::msg::dds_::Bool_/*"),
        ("/plan", "planned_path", "*/plan/nav_msgs::msg::dds_::Path_/*"),
        ("robot/outcome", "outcome", "robot/outcome"),
    ],
)
def test_a_ros_topic_is_read_on_its_rmw_zenoh_keys(name: str, kind: str, key: str) -> None:
    assert robot_key(name, kind) == key


def test_an_input_without_a_ros_type_is_not_read_as_a_topic() -> None:
    with pytest.raises(ValueError, match="outcome '/robot/outcome' is a ROS topic, but outcome is read from a zenoh"):
        robot_key("/robot/outcome", "outcome")
    with pytest.raises(ValueError, match="a TraversalOutcome has no ROS type"):
        RelayOutcomes(outcome="/robot/outcome")
    assert RelayOutcomes(planned_path="/plan").planned_path == "/plan"  # docs/calibration.md's example


def test_a_path_the_service_would_refuse_is_counted_by_the_robot_side_not_kept() -> None:
    relay, _, paths, clock = link()
    with pytest.raises(MessageError, match="PlannedPath"):
        relay.on_path("odom", 1.0, [(0.0, 0.0), (1e12, 0.0)])  # out of any grid's reach
    with pytest.raises(MessageError, match="PlannedPath"):
        relay.on_path("f" * 300, 1.0, [(0.0, 0.0)])  # a frame id longer than a message takes
    send_at(relay, clock, 0.0)
    assert paths.payloads == []
