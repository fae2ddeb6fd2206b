"""The scheduler: weighted shares, the floor, urgent changes, new sources, and the queue's glance stage."""

from __future__ import annotations

import itertools
from collections import Counter

import numpy as np
import pytest
from fakes import Clock
from gcdtrav.schemas.settings.share import ScheduleSettings
from gcdtrav.service.runtime.latest_queue import LatestFrameQueue
from gcdtrav.service.runtime.share import (
    Claim,
    FrameClass,
    Need,
    NeedShare,
    RoundRobin,
    SharePolicy,
    ambiguity_of,
)

NEWS, URGENT, REFRESH, FIRST = FrameClass.NEWS, FrameClass.URGENT, FrameClass.REFRESH, FrameClass.FIRST


class Fleet:
    """Sources whose frames are glanced at and wait with a claim: each source's class and motion."""

    def __init__(self, policy: SharePolicy, clock: Clock, motion: dict[str, float] | None = None) -> None:
        self.queue: LatestFrameQueue[str] = LatestFrameQueue(policy=policy, triage=True, clock=clock)
        self.clock, self.motion = clock, motion or {}
        self.kinds: dict[str, FrameClass] = {}

    def offer(self, source: str, kind: FrameClass | None = None, ambiguity: float = 0.0) -> None:
        """A frame of ``source``, glanced at and ready with its claim."""
        kind = self.kinds.get(source, NEWS) if kind is None else kind
        self.queue.put(source, source)
        assert self.queue.take_untriaged(timeout=0) == (source, source)
        assert self.queue.settle(source, source, Claim(kind, Need(self.motion.get(source, 0.0), ambiguity)))

    def turns(self, turns: int, inference_s: float = 1.0) -> list[str]:
        """Each take costs ``inference_s``; the source taken sends its next frame. The sources taken, in order."""
        taken = []
        for _ in range(turns):
            item = self.queue.take(timeout=0)
            assert item is not None
            taken.append(item[0])
            self.clock.now += inference_s
            self.offer(item[0])
        return taken


def run(
    policy: SharePolicy,
    clock: Clock,
    sources: list[str],
    turns: int,
    inference_s: float = 1.0,
    motion: dict[str, float] | None = None,
) -> list[str]:
    """Every source always has a frame waiting; each take costs ``inference_s``. The sources taken, in order."""
    fleet = Fleet(policy, clock, motion)
    for source in sources:
        fleet.offer(source)
        fleet.offer(source)  # a second frame: no source counts as new
    return fleet.turns(turns, inference_s)


def need(clock: Clock, **settings: float) -> NeedShare:
    return NeedShare(ScheduleSettings(**settings), clock)  # type: ignore[arg-type]


def test_round_robin_serves_one_frame_per_source_in_turn() -> None:
    clock = Clock()
    assert run(RoundRobin(clock), clock, ["a", "b", "c"], 6) == ["a", "b", "c"] * 2


def test_need_shares_inference_in_proportion_to_the_weights() -> None:
    clock = Clock()
    motion = {"fast": 1.0, "slow": 0.4}  # weights 1.2, 0.6 and the parked one's 0.2
    policy = need(clock, max_wait_s=1000.0)
    counts = Counter(run(policy, clock, ["fast", "slow", "parked"], 400, motion=motion))
    assert counts["fast"] / counts["slow"] == pytest.approx(2.0, rel=0.1)
    assert counts["fast"] / counts["parked"] == pytest.approx(6.0, rel=0.15)
    shares = policy.shares()
    assert shares["fast"].weight == pytest.approx(1.2) and shares["parked"].weight == pytest.approx(0.2)
    assert shares["fast"].share > shares["slow"].share > shares["parked"].share > 0


def test_ambiguity_ahead_counts_as_far_as_the_robot_moves() -> None:
    """A parked robot's ambiguous view keeps the base weight (its refreshes tell nothing new); a moving one's
    ambiguity ahead adds ambiguity_weight at full motion."""
    policy = need(Clock())
    assert policy.weight(Need(0.0, 1.0)) == pytest.approx(0.2)
    assert policy.weight(Need(0.5, 1.0)) == pytest.approx(0.2 + 0.5 * (1.0 + 0.5))
    assert policy.weight(Need(1.0, 1.0)) == pytest.approx(0.2 + 1.0 + 0.5)
    assert policy.weight(Need(1.0, 0.0)) == pytest.approx(1.2)
    assert policy.weight(Need(3.0, 2.0)) == pytest.approx(0.2 + 1.0 + 0.5)  # both clamped to 1


def test_the_weight_is_the_waiting_frame_s_need() -> None:
    """The policy reads a source's need from its frame: a robot that starts moving gets its share at its next
    frame, and the status shows the weight its last frame asked for."""
    clock = Clock()
    policy = need(clock, max_wait_s=1000.0)
    fleet = Fleet(policy, clock, {"a": 1.0})
    for source in ("a", "a", "b", "b"):
        fleet.offer(source)
    first = Counter(fleet.turns(70))
    assert first["b"] == pytest.approx(10, abs=1)  # 1.2 against 0.2
    fleet.motion["b"] = 1.0  # b starts moving: its next frame says so
    assert Counter(fleet.turns(70))["b"] == pytest.approx(35, abs=2)
    assert policy.shares()["b"].weight == pytest.approx(1.2)


def test_equal_weights_are_round_robin() -> None:
    clock = Clock()
    taken = run(need(clock), clock, ["a", "b", "c"], 9)
    assert Counter(taken) == {"a": 3, "b": 3, "c": 3}
    assert all(len(set(taken[k : k + 3])) == 3 for k in range(0, 9, 3))


@pytest.mark.parametrize("max_wait_s", [3.0, 5.0])
def test_the_floor_no_source_waits_longer_than_max_wait_s_plus_one_inference(max_wait_s: float) -> None:
    clock = Clock()
    motion = {f"m{k}": 1.0 for k in range(3)}
    policy = need(clock, max_wait_s=max_wait_s, base_weight=0.01)
    taken = run(policy, clock, ["m0", "m1", "m2", "parked"], 200, motion=motion)
    turns = [k for k, source in enumerate(taken) if source == "parked"]
    waits = np.diff([-1, *turns])  # in inferences of 1 s; the first waits since t = 0
    assert len(turns) >= 200 / (max_wait_s + 2) - 1
    assert waits.max() <= max_wait_s + 1


def test_one_source_is_always_served() -> None:
    clock = Clock()
    assert run(need(clock), clock, ["only"], 5) == ["only"] * 5


def test_urgent_changes_go_next_but_take_at_most_every_other_turn() -> None:
    clock = Clock()
    fleet = Fleet(need(clock, max_wait_s=1000.0), clock, {"m0": 1.0, "m1": 1.0})
    fleet.kinds = {"flip0": URGENT, "flip1": URGENT}  # views that keep changing after reuse
    for source in ("m0", "m1", "flip0", "flip1"):
        fleet.offer(source)
        fleet.offer(source)
    taken = fleet.turns(12)
    assert taken[0].startswith("flip")
    assert all(not (a.startswith("flip") and b.startswith("flip")) for a, b in itertools.pairwise(taken))
    assert sum(source.startswith("m") for source in taken) == 6


def refresh_turns(policy: NeedShare, clock: Clock, movers: list[str], turns: int) -> list[int]:
    """Movers always wait; a parked source's refresh waits again right after each turn. Its turns' indices."""
    fleet = Fleet(policy, clock)
    fleet.kinds["parked"] = REFRESH
    for source in [*movers, "parked", "parked", *movers]:
        fleet.offer(source)
    return [k for k, source in enumerate(fleet.turns(turns)) if source == "parked"]


@pytest.mark.parametrize("movers", [1, 3])
def test_a_refresh_yields_to_every_other_frame_until_the_floor(movers: int) -> None:
    clock = Clock()
    policy = need(clock, max_wait_s=5.0)  # every weight the base one: weighted, the refresh would go in turn
    turns = refresh_turns(policy, clock, [f"m{k}" for k in range(movers)], 60)
    waits = np.diff([-1, *turns])  # in inferences of 1 s
    # Yielding, it goes only once it is overdue: after max_wait_s, and never later than one inference after.
    assert len(turns) >= 60 / 7 - 1
    assert waits.min() >= 5 and waits.max() <= 6 + 1


def test_a_refresh_alone_goes_at_once_and_one_not_marked_is_weighted() -> None:
    clock = Clock()
    policy = need(clock, max_wait_s=5.0)
    assert refresh_turns(policy, clock, [], 3) == [0, 1, 2]  # nothing else waits: the box has room
    clock = Clock()
    policy = need(clock, max_wait_s=1000.0)
    counts = Counter(run(policy, clock, ["m0", "parked"], 70, motion={"m0": 1.0}))  # news: weights 1.2 and 0.2
    assert counts["parked"] == pytest.approx(10, abs=1)


def test_a_change_ends_a_refresh_and_so_does_its_turn() -> None:
    clock = Clock()
    fleet = Fleet(need(clock, max_wait_s=1000.0), clock, {"m0": 1.0})
    for source, kind in (("m0", NEWS), ("m0", NEWS), ("parked", NEWS), ("parked", REFRESH)):
        fleet.offer(source, kind)
    assert fleet.queue.take(timeout=0) == ("m0", "m0")
    fleet.offer("m0")
    fleet.offer("parked", URGENT)  # the view changed while its refresh waited: it goes next
    assert fleet.queue.take(timeout=0) == ("parked", "parked")
    # Its turn ended the class: a frame of it waiting again (not a refresh) is weighted, 0.2 against 1.2.
    fleet.offer("parked")
    counts = Counter(fleet.turns(70))
    assert counts["parked"] == pytest.approx(10, abs=2)
    fleet.offer("parked", REFRESH)
    fleet.offer("parked", NEWS)  # a newer frame with news replaced the refresh
    assert Counter(fleet.turns(70))["parked"] == pytest.approx(10, abs=2)


def test_an_urgent_wait_stays_urgent_until_its_turn_and_a_first_frame_until_more_comes() -> None:
    """The ready slot's class: urgent whatever newer frame replaces it before its turn (its consumers still hold
    a view that is gone); a source's first frame is first only until anything more is received from it."""
    clock = Clock()
    fleet = Fleet(need(clock, max_wait_s=1000.0), clock, {"m0": 1.0})
    for source in ("m0", "m0", "parked", "parked"):
        fleet.offer(source, NEWS)
    assert fleet.queue.take(timeout=0) == ("m0", "m0")  # weights 1.2 and 0.2
    fleet.offer("m0")
    fleet.offer("parked", URGENT)
    fleet.offer("parked", REFRESH)  # a refresh replaced the urgent frame before its turn: still urgent
    assert fleet.queue.take(timeout=0) == ("parked", "parked")
    fleet.offer("parked", REFRESH)
    assert fleet.turns(2) == ["m0", "m0"]  # the turn ended the urgency: the refresh yields

    queue: LatestFrameQueue[str] = LatestFrameQueue(policy=RoundRobin(clock), clock=clock)
    for k in range(3):
        queue.put(f"new{k}", "n")
    queue.put("new0", "again")  # a second frame: new0 is no stranger
    queue.count_unqueued("new1")  # one refused before queueing counts too
    clock.now += 1.0
    queue.put("robot", "x")
    queue.put("robot", "y")
    # Only new2 is still first: without the demotion the robot would go second, after new0.
    taken = [queue.take(timeout=0) for _ in range(4)]
    assert taken == [("new0", "again"), ("new1", "n"), ("new2", "n"), ("robot", "y")]


def test_one_every_other_turn_rule_for_first_and_urgent_frames_and_round_robin_limits_first_only() -> None:
    """A limited class takes at most every other turn while another class waits, even at the floor; the need
    policy limits first and urgent frames, round-robin (which favours no class) first frames only."""
    clock = Clock()
    fleet = Fleet(need(clock, max_wait_s=2.0), clock)
    for source in ("flip0", "flip0", "flip1", "flip1"):
        fleet.offer(source, URGENT)
    clock.now += 1.0
    fleet.offer("robot")
    fleet.offer("robot")
    clock.now += 10.0  # everything is over the floor, the flips the longest
    assert [item[0] for item in (fleet.queue.take(timeout=0) for _ in range(3)) if item] == ["flip0", "robot", "flip1"]

    clock = Clock()
    fleet = Fleet(RoundRobin(clock), clock)
    for source in ("flip0", "flip0", "flip1", "flip1", "robot", "robot"):
        fleet.offer(source, URGENT if source.startswith("flip") else NEWS)
    assert [item[0] for item in (fleet.queue.take(timeout=0) for _ in range(3)) if item] == ["flip0", "flip1", "robot"]


def test_a_new_source_still_takes_at_most_every_other_turn() -> None:
    clock = Clock()
    queue: LatestFrameQueue[str] = LatestFrameQueue(policy=need(clock), clock=clock)
    queue.put("robot", "x")
    queue.put("robot", "x")  # two frames: a returning source
    taken = []
    for k in range(6):
        queue.put(f"new{k}", "n")
        queue.put("robot", "x")
        item = queue.take(timeout=0)
        assert item is not None
        taken.append(item[0])
        clock.now += 1.0
    assert all(not (a.startswith("new") and b.startswith("new")) for a, b in itertools.pairwise(taken))


def test_triage_frames_wait_for_their_glance_and_counters_add_up() -> None:
    queue: LatestFrameQueue[str] = LatestFrameQueue(triage=True)
    queue.put("a", "a1", 10)
    assert queue.take(timeout=0) is None  # not glanced at yet
    assert queue.take_untriaged(timeout=0) == ("a", "a1")
    queue.put("a", "a2", 10)  # replaces the arrival being glanced at
    assert not queue.settle("a", "a1", Claim())  # stale verdict: nothing changes
    assert queue.take_untriaged(timeout=0) == ("a", "a2")
    assert queue.settle("a", "a2", Claim())
    queue.put("a", "a3", 10)
    assert queue.take_untriaged(timeout=0) == ("a", "a3")
    assert queue.has_ready("a") and len(queue) == 2 and queue.nbytes == 20
    assert queue.settle("a", "a3", None)  # answered with the last maps: leaves the queue
    assert queue.take(timeout=0) == ("a", "a2")
    assert len(queue) == 0 and queue.nbytes == 0
    queue.put("a", "a4", 10)
    queue.take_untriaged(timeout=0)
    queue.settle("a", "a4", Claim())
    queue.put("a", "a5", 10)
    queue.take_untriaged(timeout=0)
    queue.settle("a", "a5", Claim())  # replaces the ready a4: dropped
    counters = queue.counters()["a"]
    assert counters.received == 5 and counters.dropped == 2  # a1 replaced while glanced, a4 replaced when ready
    # received 5 = taken a2 + reused a3 + dropped a1, a4 + waiting a5
    assert queue.discard_pending() == {"a": 1}


def test_forget_clears_both_stages_and_the_policy() -> None:
    clock = Clock()
    policy = need(clock)
    queue: LatestFrameQueue[str] = LatestFrameQueue(policy=policy, triage=True, clock=clock)
    queue.put("a", "a1", 5)
    queue.take_untriaged(timeout=0)
    queue.settle("a", "a1", Claim(NEWS, Need(1.0, 0.5)))
    assert queue.take(timeout=0) == ("a", "a1") and policy.shares()["a"].weight == pytest.approx(1.45)
    queue.put("a", "a2", 5)
    queue.take_untriaged(timeout=0)
    queue.settle("a", "a2", Claim())
    queue.put("a", "a3", 5)
    queue.forget("a")
    assert len(queue) == 0 and queue.nbytes == 0 and "a" not in policy.shares()
    assert not queue.settle("a", "a3", None)


def test_ambiguity_counts_the_lower_half_only() -> None:
    settings = ScheduleSettings(ambiguous_u=0.2, novel_match=0.3)
    u = np.zeros((8, 8), np.float32)
    u[:4] = 0.4  # the sky: ignored
    assert ambiguity_of(u, None, settings) == 0.0
    u[6:] = 0.25
    assert ambiguity_of(u, None, settings) == 0.5
    match = np.ones((8, 8), np.float32)
    match[4] = 0.1  # novel ground
    assert ambiguity_of(u, match, settings) == 0.75
    assert ambiguity_of(u, match, ScheduleSettings(ambiguous_u=0.2)) == 0.5  # novel_match 0: not used
