"""The scheduler: weighted shares, the floor, urgent changes, new sources, and the queue's glance stage."""

from __future__ import annotations

import itertools
from collections import Counter

import numpy as np
import pytest
from fakes import Clock
from gcdtrav.schemas.settings.share import ScheduleSettings
from gcdtrav.service.runtime.latest_queue import LatestFrameQueue
from gcdtrav.service.runtime.share import NeedShare, RoundRobin, SharePolicy, ambiguity_of


def run(policy: SharePolicy, clock: Clock, sources: list[str], turns: int, inference_s: float = 1.0) -> list[str]:
    """Every source always has a frame waiting; each take costs ``inference_s``. The sources taken, in order."""
    queue: LatestFrameQueue[str] = LatestFrameQueue(policy=policy, clock=clock)
    for source in sources:
        queue.put(source, source)
        queue.put(source, source)  # a second frame: no source counts as new
    taken = []
    for _ in range(turns):
        item = queue.take(timeout=0)
        assert item is not None
        taken.append(item[0])
        clock.now += inference_s
        queue.put(item[0], item[0])
    return taken


def need(clock: Clock, motion: dict[str, float], **settings: float) -> NeedShare:
    return NeedShare(ScheduleSettings(**settings), lambda s: motion.get(s, 0.0), clock)  # type: ignore[arg-type]


def test_round_robin_serves_one_frame_per_source_in_turn() -> None:
    clock = Clock()
    assert run(RoundRobin(clock), clock, ["a", "b", "c"], 6) == ["a", "b", "c"] * 2


def test_need_shares_inference_in_proportion_to_the_weights() -> None:
    clock = Clock()
    motion = {"fast": 1.0, "slow": 0.4}  # weights 1.2, 0.6 and the parked one's 0.2
    policy = need(clock, motion, max_wait_s=1000.0)
    counts = Counter(run(policy, clock, ["fast", "slow", "parked"], 400))
    assert counts["fast"] / counts["slow"] == pytest.approx(2.0, rel=0.1)
    assert counts["fast"] / counts["parked"] == pytest.approx(6.0, rel=0.15)
    shares = policy.shares()
    assert shares["fast"].weight == pytest.approx(1.2) and shares["parked"].weight == pytest.approx(0.2)
    assert shares["fast"].share > shares["slow"].share > shares["parked"].share > 0


def test_ambiguity_ahead_counts_as_far_as_the_robot_moves() -> None:
    """A parked robot's ambiguous view keeps the base weight (its refreshes tell nothing new); a moving one's
    ambiguity ahead adds ambiguity_weight at full motion."""
    clock = Clock()
    policy = need(clock, {"moving": 1.0, "half": 0.5, "parked": 0.0})
    for source in ("moving", "half", "parked"):
        policy.set_ambiguity(source, 1.0)
    assert policy.weight("parked") == pytest.approx(0.2)
    assert policy.weight("half") == pytest.approx(0.2 + 0.5 * (1.0 + 0.5))
    assert policy.weight("moving") == pytest.approx(0.2 + 1.0 + 0.5)
    policy.set_ambiguity("moving", 0.0)
    assert policy.weight("moving") == pytest.approx(1.2)


def test_equal_weights_are_round_robin() -> None:
    clock = Clock()
    taken = run(need(clock, {}), clock, ["a", "b", "c"], 9)
    assert Counter(taken) == {"a": 3, "b": 3, "c": 3}
    assert all(len(set(taken[k : k + 3])) == 3 for k in range(0, 9, 3))


@pytest.mark.parametrize("max_wait_s", [3.0, 5.0])
def test_the_floor_no_source_waits_longer_than_max_wait_s_plus_one_inference(max_wait_s: float) -> None:
    clock = Clock()
    motion = {f"m{k}": 1.0 for k in range(3)}
    policy = need(clock, motion, max_wait_s=max_wait_s, base_weight=0.01)
    taken = run(policy, clock, ["m0", "m1", "m2", "parked"], 200)
    turns = [k for k, source in enumerate(taken) if source == "parked"]
    waits = np.diff([-1, *turns])  # in inferences of 1 s; the first waits since t = 0
    assert len(turns) >= 200 / (max_wait_s + 2) - 1
    assert waits.max() <= max_wait_s + 1


def test_one_source_is_always_served() -> None:
    clock = Clock()
    assert run(need(clock, {}), clock, ["only"], 5) == ["only"] * 5


def test_urgent_changes_go_next_but_take_at_most_every_other_turn() -> None:
    clock = Clock()
    policy = need(clock, {"m0": 1.0, "m1": 1.0}, max_wait_s=1000.0)
    queue: LatestFrameQueue[str] = LatestFrameQueue(policy=policy, clock=clock)
    for source in ("m0", "m1", "flip0", "flip1"):
        queue.put(source, source)
        queue.put(source, source)
    taken = []
    for _ in range(12):
        for flip in ("flip0", "flip1"):
            policy.mark_urgent(flip)  # views that keep changing after reuse
        item = queue.take(timeout=0)
        assert item is not None
        taken.append(item[0])
        clock.now += 1.0
        queue.put(item[0], item[0])
    assert taken[0].startswith("flip")
    assert all(not (a.startswith("flip") and b.startswith("flip")) for a, b in itertools.pairwise(taken))
    assert sum(source.startswith("m") for source in taken) == 6


def refresh_turns(policy: NeedShare, clock: Clock, movers: list[str], turns: int) -> list[int]:
    """Movers always wait; a parked source's refresh waits again right after each turn. Its turns' indices."""
    queue: LatestFrameQueue[str] = LatestFrameQueue(policy=policy, clock=clock)
    for source in [*movers, "parked", "parked"]:
        queue.put(source, source)
    for source in movers:
        queue.put(source, source)
    policy.mark_refresh("parked", True)
    taken = []
    for k in range(turns):
        item = queue.take(timeout=0)
        assert item is not None
        clock.now += 1.0
        queue.put(item[0], item[0])
        if item[0] == "parked":
            taken.append(k)
            policy.mark_refresh("parked", True)
    return taken


@pytest.mark.parametrize("movers", [1, 3])
def test_a_refresh_yields_to_every_other_frame_until_the_floor(movers: int) -> None:
    clock = Clock()
    policy = need(clock, {}, max_wait_s=5.0)  # every weight the base one: weighted, the refresh would go in turn
    turns = refresh_turns(policy, clock, [f"m{k}" for k in range(movers)], 60)
    waits = np.diff([-1, *turns])  # in inferences of 1 s
    # Yielding, it goes only once it is overdue: after max_wait_s, and never later than one inference after.
    assert len(turns) >= 60 / 7 - 1
    assert waits.min() >= 5 and waits.max() <= 6 + 1


def test_a_refresh_alone_goes_at_once_and_one_not_marked_is_weighted() -> None:
    clock = Clock()
    policy = need(clock, {}, max_wait_s=5.0)
    assert refresh_turns(policy, clock, [], 3) == [0, 1, 2]  # nothing else waits: the box has room
    clock = Clock()
    policy = need(clock, {"m0": 1.0}, max_wait_s=1000.0)
    counts = Counter(run(policy, clock, ["m0", "parked"], 70))  # no refresh marked: weights 1.2 and 0.2
    assert counts["parked"] == pytest.approx(10, abs=1)


def test_a_change_ends_a_refresh_and_so_does_its_turn() -> None:
    clock = Clock()
    policy = need(clock, {"m0": 1.0}, max_wait_s=1000.0)
    queue: LatestFrameQueue[str] = LatestFrameQueue(policy=policy, clock=clock)
    for source in ("m0", "m0", "parked", "parked"):
        queue.put(source, source)
    policy.mark_refresh("parked", True)
    assert queue.take(timeout=0) == ("m0", "m0")
    queue.put("m0", "m0")
    policy.mark_urgent("parked")  # the view changed while its refresh waited: it goes next
    assert queue.take(timeout=0) == ("parked", "parked")
    # Its turn ended the mark: a frame of it waiting again (not a refresh) is weighted, 0.2 against 1.2.
    queue.put("parked", "parked")
    counts = Counter(run_queue(queue, clock, 70))
    assert counts["parked"] == pytest.approx(10, abs=2)
    policy.mark_refresh("parked", True)
    policy.mark_refresh("parked", False)  # a newer frame with news replaced the refresh
    assert Counter(run_queue(queue, clock, 70))["parked"] == pytest.approx(10, abs=2)


def run_queue(queue: LatestFrameQueue[str], clock: Clock, turns: int) -> list[str]:
    """Like ``run`` on an existing queue: each source taken sends its next frame."""
    taken = []
    for _ in range(turns):
        item = queue.take(timeout=0)
        assert item is not None
        taken.append(item[0])
        clock.now += 1.0
        queue.put(item[0], item[0])
    return taken


def test_a_new_source_still_takes_at_most_every_other_turn() -> None:
    clock = Clock()
    queue: LatestFrameQueue[str] = LatestFrameQueue(policy=need(clock, {}), clock=clock)
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
    assert not queue.settle("a", "a1", reused=False)  # stale verdict: nothing changes
    assert queue.take_untriaged(timeout=0) == ("a", "a2")
    assert queue.settle("a", "a2", reused=False)
    queue.put("a", "a3", 10)
    assert queue.take_untriaged(timeout=0) == ("a", "a3")
    assert queue.has_ready("a") and len(queue) == 2 and queue.nbytes == 20
    assert queue.settle("a", "a3", reused=True)  # answered with the last maps: leaves the queue
    assert queue.take(timeout=0) == ("a", "a2")
    assert len(queue) == 0 and queue.nbytes == 0
    queue.put("a", "a4", 10)
    queue.take_untriaged(timeout=0)
    queue.settle("a", "a4", reused=False)
    queue.put("a", "a5", 10)
    queue.take_untriaged(timeout=0)
    queue.settle("a", "a5", reused=False)  # replaces the ready a4: dropped
    counters = queue.counters()["a"]
    assert counters.received == 5 and counters.dropped == 2  # a1 replaced while glanced, a4 replaced when ready
    # received 5 = taken a2 + reused a3 + dropped a1, a4 + waiting a5
    assert queue.discard_pending() == {"a": 1}


def test_forget_clears_both_stages_and_the_policy() -> None:
    clock = Clock()
    policy = need(clock, {})
    queue: LatestFrameQueue[str] = LatestFrameQueue(policy=policy, triage=True, clock=clock)
    queue.put("a", "a1", 5)
    queue.take_untriaged(timeout=0)
    queue.settle("a", "a1", reused=False)
    queue.put("a", "a2", 5)
    policy.set_ambiguity("a", 0.5)
    queue.forget("a")
    assert len(queue) == 0 and queue.nbytes == 0 and "a" not in policy.shares()
    assert not queue.settle("a", "a2", reused=True)


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
