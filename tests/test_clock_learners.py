"""The three learners of a clock from the smallest delay learn alike (issue 50): a source's clock at intake
(service/runtime/intake/clock_offset.py), a grid's pose stream (service/grid/poses.py) and a relay's camera
(client/relay/state.py CameraClock), fed the same stamps and receipts, hold the same offset after every
sample: through jitter, stamps out of order, an outage longer than the window, the window rolling over, and
the robot's clock stepping forward and back. The grid's status subtracts two of them (``pose_clock_s``): a
learner that learnt differently would show as a clock difference that is not there."""

from __future__ import annotations

import pytest
from gcdtrav.client.relay.state import CameraClock
from gcdtrav.schemas.messages import Pose2D
from gcdtrav.service.grid.poses import PoseBuffer
from gcdtrav.service.runtime.intake.clock_offset import ClockOffsets


def samples() -> list[tuple[float, float]]:
    """(stamp on the robot's clock, receipt on the service's): the service's clock is the robot's plus 100 s."""
    found: list[tuple[float, float]] = []
    receipt = 1000.0

    def stream(seconds: float, hz: float, delay: float, clock_step: float = 0.0) -> None:
        nonlocal receipt
        for k in range(round(seconds * hz)):
            receipt += 1 / hz
            jitter = 0.02 * (k % 5)  # the link's delay varies; every fifth frame is the fastest
            found.append((receipt - 100.0 + clock_step - delay - jitter, receipt))

    stream(10.0, 10.0, 0.05)
    found[20], found[21] = (
        (found[21][0], found[20][1]),
        (found[20][0], found[21][1]),
    )  # stamps out of order: 20 seems the fastest
    stream(10.0, 0.5, 0.05)  # 2 s gaps: each counts 1 s of the window
    receipt += 60.0  # an outage, longer than the window
    stream(40.0, 10.0, 0.3)  # a slower link: learnt once the faster frames leave the window
    stream(10.0, 10.0, 0.3, clock_step=5.0)  # the robot's clock steps forward: smaller delays, learnt at once
    stream(40.0, 10.0, 0.3, clock_step=2.0)  # back by 3 s: larger delays, learnt as the window rolls over
    return found


def test_the_three_learners_hold_the_same_offset_after_every_sample() -> None:
    intake = ClockOffsets(max_lag_s=None, max_ahead_s=None)  # no limits: every frame is fresh and learnt
    poses = PoseBuffer(span_s=1e6, max_poses=100_000, extrapolate_s=0.1, max_gap_s=0.5)
    relay = CameraClock()
    learnt = []
    for stamp, received_at in samples():
        reading = intake.observe("r1/front", stamp, received_at)
        poses.add(Pose2D(stamp=stamp, x=0.0, y=0.0, yaw=0.0), received_at)
        relay.add(stamp, received_at)
        assert poses.offset_s == pytest.approx(reading.offset_s, abs=1e-9), (stamp, received_at)
        assert relay.offset_s() == pytest.approx(reading.offset_s, abs=1e-9), (stamp, received_at)
        learnt.append(reading.offset_s)
    # What they learnt together, at the end of each stretch: the fastest frame, kept through the gaps and the
    # outage; the slower link once the window rolled over; the step forward at once; the step back as the
    # window rolled over again.
    ends = [99, 104, 504, 604, 1004]
    assert [round(learnt[end], 6) for end in ends] == [99.97, 99.97, 100.3, 95.3, 98.3]
    assert round(learnt[105], 6) == 99.97  # the first frame after the outage: the clock learnt before it
    assert round(learnt[505], 6) == 95.3  # the first frame after the step forward
