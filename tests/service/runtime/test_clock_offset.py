"""Freshness from delay, not from two clocks: robots whose clocks are wrong, or step, are served; a link's
backlog is still dropped. Streams are simulated with their true capture times, the robot's stamps and the
receipts here (jittered delays), through the one freshness rule as the intake judges them."""

from __future__ import annotations

import logging
import random
from dataclasses import dataclass

import pytest
from gcdtrav.schemas.delay_window import WINDOW_S
from gcdtrav.schemas.inputs import RejectedInput
from gcdtrav.service.runtime.intake.clock_offset import STEP_HOLD_S, ClockOffsets
from gcdtrav.service.runtime.intake.freshness import Dropped, Freshness

HOUR = 3600.0
FPS = 15.0
MAX_AGE_S = 5.0
SKEW_S = 300.0
T0 = 1_790_000_000.0  # the service's clock at the start, 2026


@dataclass(frozen=True)
class Frame:
    captured: float  # true capture time, the service's clock
    stamp: float  # the robot's clock
    received: float  # here


def stream(
    seconds: float,
    offset: float = 0.0,
    start: float = T0,
    fps: float = FPS,
    base_delay: float = 0.02,
    seed: int = 0,
) -> list[Frame]:
    """Frames at ``fps`` stamped by a robot clock ``offset`` ahead of the service's, 20-80 ms on the link."""
    rng = random.Random(seed)
    frames = []
    for k in range(round(seconds * fps)):
        captured = start + k / fps
        frames.append(Frame(captured, captured + offset, captured + base_delay + rng.uniform(0, 0.06)))
    return frames


@dataclass
class Outcome:
    served: list[Frame]
    stale: list[Frame]
    skewed: list[Frame]


def judge(rule: Freshness, frames: list[Frame], source: str = "r1/front") -> Outcome:
    outcome = Outcome([], [], [])
    for frame in frames:
        refusal = rule.at_intake(source, frame.stamp, frame.received).refusal
        if refusal is None:
            outcome.served.append(frame)
        elif isinstance(refusal, Dropped):
            assert refusal.reason == "stale"
            outcome.stale.append(frame)
        else:
            assert isinstance(refusal, RejectedInput) and refusal.reason == "skewed_stamp"
            outcome.skewed.append(frame)
    return outcome


def estimated(max_age_s: float | None = MAX_AGE_S, skew_s: float | None = SKEW_S) -> Freshness:
    return Freshness(max_age_s, skew_s, "estimated", logging.getLogger("gcdtrav.test"))


@pytest.mark.parametrize("offset", [-HOUR, HOUR, 0.0, -10 * 365 * 24 * HOUR, 0.9, -0.9])
def test_a_robot_whose_clock_is_off_by_any_amount_has_every_frame_served(offset: float) -> None:
    rule = estimated()
    frames = stream(20, offset)
    outcome = judge(rule, frames)
    assert outcome.served == frames
    learnt = rule.offsets.offsets().get("r1/front")
    assert learnt is not None and -offset + 0.02 <= learnt <= -offset + 0.03  # plus the link's smallest delay


@pytest.mark.parametrize("offset", [-HOUR, HOUR])
def test_with_clock_synced_the_same_robot_gets_nothing_and_is_told_why(offset: float) -> None:
    rule = Freshness(MAX_AGE_S, SKEW_S, "synced")
    outcome = judge(rule, stream(5, offset))
    assert not outcome.served
    assert outcome.stale if offset < 0 else outcome.skewed  # behind: too old; ahead: from the future
    learnt = rule.offsets.offsets().get("r1/front")
    assert learnt is not None and abs(learnt + offset) < 0.1  # still learnt, for the status


def test_synced_with_clocks_in_step_serves_everything() -> None:
    frames = stream(5)
    assert judge(Freshness(MAX_AGE_S, SKEW_S, "synced"), frames).served == frames


def test_the_offset_is_warned_once_per_source_beyond_a_second_and_rarely_overall(
    caplog: pytest.LogCaptureFixture,
) -> None:
    rule = estimated()
    with caplog.at_level(logging.WARNING, "gcdtrav.test"):
        judge(rule, stream(3, -HOUR), "behind")
        judge(rule, stream(3, 0.5), "close")
        for k in range(100):  # invented names with wrong clocks, each forgotten when refused
            judge(rule, stream(0.2, HOUR), f"invented{k}")
            rule.offsets.forget(f"invented{k}")
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 1 and warnings[0].startswith("behind: clock offset +3600.0")
    assert "clock: estimated" in warnings[0]


@pytest.mark.parametrize("step", [-HOUR, -30.0, HOUR, 1000.0])
def test_a_clock_step_beyond_the_limits_costs_about_a_second_of_frames_then_is_learnt(step: float) -> None:
    rule = estimated()
    before = stream(10, 0.0)
    after = stream(10, step, start=before[-1].captured + 1 / FPS, seed=1)
    first = judge(rule, before)
    assert first.served == before
    outcome = judge(rule, after)
    lost = outcome.stale if step < 0 else outcome.skewed
    assert not (outcome.skewed if step < 0 else outcome.stale)
    assert STEP_HOLD_S * FPS <= len(lost) <= (STEP_HOLD_S + 0.2) * FPS
    assert outcome.served == after[len(lost) :]  # every frame after the step is learnt
    learnt = rule.offsets.offsets().get("r1/front")
    assert learnt is not None and abs(learnt + step) < 0.1


@pytest.mark.parametrize("step", [-2.0, -4.9, 2.0, 250.0])
def test_a_clock_step_within_the_limits_loses_no_frame(step: float) -> None:
    rule = estimated()
    before = stream(10)
    after = stream(40, step, start=before[-1].captured + 1 / FPS, seed=2)
    assert judge(rule, before).served == before
    assert judge(rule, after).served == after
    learnt = rule.offsets.offsets().get("r1/front")
    # forward at once; back as the older, smaller delays leave the window
    assert learnt is not None and abs(learnt + step) < 0.1


def outage(seconds: float, backlog_rate: float, offset: float = -HOUR) -> tuple[list[Frame], list[Frame]]:
    """A stream, then an outage of ``seconds``: the link delivers what it buffered ``backlog_rate`` times as
    fast as frames are captured, then keeps up. (before, after) in order of receipt."""
    before = stream(10, offset)
    down_at = before[-1].captured + 1 / FPS
    up_at = down_at + seconds
    after, previous, spacing = [], up_at, (1 / FPS) / backlog_rate
    drained_s = seconds / (backlog_rate - 1)
    for frame in stream(seconds + drained_s + 10, offset, start=down_at, seed=3):  # first in, first out
        arrives = max(frame.received, up_at) if frame.captured < up_at else frame.received
        previous = max(arrives, previous + spacing)
        after.append(Frame(frame.captured, frame.stamp, previous))
    return before, after


@pytest.mark.parametrize(("seconds", "rate"), [(10.0, 4.0), (10.0, 1.5), (WINDOW_S * 2, 3.0), (10.0, 1000.0)])
def test_a_backlog_after_an_outage_is_dropped_not_learnt(seconds: float, rate: float) -> None:
    rule = estimated()
    before, after = outage(seconds, rate)
    judge(rule, before)
    learnt = rule.offsets.offsets().get("r1/front")
    outcome = judge(rule, after)
    too_old = [f for f in after if f.received - f.captured > MAX_AGE_S + 0.08]
    young = [f for f in after if f.received - f.captured <= MAX_AGE_S]
    assert too_old and all(f in outcome.stale for f in too_old)
    assert young and all(f in outcome.served for f in young)
    assert outcome.served[-150:] == after[-150:]  # caught up: the last 10 s are all served
    assert rule.offsets.offsets().get("r1/front") == pytest.approx(learnt, abs=0.05)  # not taken for a step


def test_a_frame_stamped_far_ahead_once_is_rejected_and_changes_nothing() -> None:
    rule = estimated()
    frames = stream(6)
    glitch = frames[40]
    frames[40] = Frame(glitch.captured, glitch.stamp + 10 * HOUR, glitch.received)
    outcome = judge(rule, frames)
    assert outcome.skewed == [frames[40]] and not outcome.stale and len(outcome.served) == len(frames) - 1


def test_bare_images_carry_no_stamp_and_teach_no_clock() -> None:
    rule = estimated()
    age = rule.at_intake("cam", None, T0)
    assert age.lag_s is None and age.refusal is None and "cam" not in rule.offsets.offsets()
    for bad in (float("nan"), float("inf"), -1.0):  # the decoder rejects them (bad_stamp), the clock ignores them
        assert rule.at_intake("cam", bad, T0) == age


def test_a_sources_first_frame_sets_its_clock() -> None:
    rule = estimated()
    first = rule.at_intake("new", T0 - HOUR, T0)
    assert first.refusal is None and first.lag_s == 0.0 and rule.offsets.offsets() == {"new": HOUR}
    synced = Freshness(MAX_AGE_S, SKEW_S, "synced")
    assert isinstance(synced.at_intake("new", T0 - HOUR, T0).refusal, Dropped)


def test_replayed_bags_without_an_age_limit_are_served_through_loops_and_learnt() -> None:
    """A 2023 bag replayed in real time, looping every 20 s, max_frame_age_s null, under either clock."""
    bag_start = 1_690_000_000.0
    for clock in ("estimated", "synced"):
        rule = Freshness(None, SKEW_S, clock)  # type: ignore[arg-type]
        frames = []
        for loop in range(3):
            for frame in stream(20, start=T0 + loop * 20, seed=loop):
                frames.append(Frame(frame.captured, bag_start + (frame.captured - T0 - loop * 20), frame.received))
        assert judge(rule, frames).served == frames
        learnt = rule.offsets.offsets().get("r1/front")
        assert learnt is not None and learnt > T0 - bag_start - 1


def test_the_age_later_adds_the_time_waited_here_and_a_negative_lag_ages_nothing() -> None:
    from gcdtrav.service.runtime.intake.freshness import _age

    assert _age(2.0, waited_s=1.5) == 3.5
    assert _age(-3.0, waited_s=1.5) == 1.5
    assert _age(None, waited_s=1.5) == 1.5


@pytest.mark.parametrize("limit", [0.0, -1.0])
def test_max_frame_age_must_be_positive(limit: float) -> None:
    with pytest.raises(ValueError, match="positive"):
        Freshness(limit, None)


def test_forgotten_sources_learn_again() -> None:
    offsets = ClockOffsets(MAX_AGE_S, SKEW_S)
    offsets.observe("a", T0, T0 + HOUR)
    assert offsets.offsets() == {"a": HOUR}
    offsets.forget("a")
    assert offsets.observe("a", T0, T0 - HOUR).lag_s == 0.0 and offsets.offsets() == {"a": -HOUR}
