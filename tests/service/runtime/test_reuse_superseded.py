"""A frame judged reusable against one reference is never answered with the maps of another view: newer maps
kept between its glance and its answer (the worker's hand-off out) must fit it too, else it is dropped."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from fakes import Clock
from gcdtrav.schemas.messages import credits
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.runtime.frames import PendingFrame
from gcdtrav.service.runtime.schedule.latest_queue import LatestFrameQueue
from gcdtrav.service.runtime.schedule.share import policy_for
from gcdtrav.service.runtime.stats import ServiceStats
from gcdtrav.service.runtime.triage.change import Glance
from gcdtrav.service.runtime.triage.reuse import Republished, ReuseTracker, Triage
from numpy.typing import NDArray
from scenes import jpeg_frame, noisy, scene, with_person

LOG = __import__("logging").getLogger("test")
SOURCE = "parked"


class Answers:
    def __init__(self) -> None:
        self.put: list[PendingFrame] = []
        self.freed: list[str] = []

    def republish(self, pending: PendingFrame, seen: Glance, fits: Callable[[], bool]) -> Republished:
        if not fits():
            return Republished.SUPERSEDED
        self.put.append(pending)
        return Republished.PUT


def glanced_reusable(between: NDArray[np.uint8] | None) -> tuple[Answers, ServiceStats, PendingFrame]:
    """A parked robot's view inferred; its next frame judged reusable; then (before that frame is answered)
    the worker keeps the maps of ``between`` (None: nothing kept meanwhile); then the frame is answered."""
    config = ServiceSettings()
    clock, stats, answers = Clock(), ServiceStats(LOG), Answers()
    tracker = ReuseTracker(config.reuse, config.schedule, clock=clock)
    queue: LatestFrameQueue[PendingFrame] = LatestFrameQueue(
        policy=policy_for(config.schedule), triage=True, clock=clock
    )
    triage = Triage(queue, tracker, config, stats, answers.republish, lambda p, reason: answers.freed.append(reason))
    view = scene()
    first = jpeg_frame(view, SOURCE, received_at=100.0)
    tracker.inferred(SOURCE, first, view)
    clock.now += 0.1
    later = jpeg_frame(noisy(view, 4.0, 1), SOURCE, received_at=100.1)
    queue.put(SOURCE, later)
    reusable = triage.next_reusable(0)
    assert reusable is not None and reusable.pending is later  # unchanged against the first view
    if between is not None:  # the worker's next frame: its maps kept, it the reference, before the answer
        tracker.inferred(SOURCE, jpeg_frame(between, SOURCE, received_at=100.05), between)
    triage.reuse(reusable)
    return answers, stats, later


def test_a_frame_judged_unchanged_is_answered_while_its_reference_stands() -> None:
    answers, stats, later = glanced_reusable(None)
    assert answers.put == [later] and answers.freed == [credits.UNCHANGED]
    assert stats.snapshot({}).sources[SOURCE].unchanged == 1


def test_newer_maps_of_the_same_view_still_answer_it() -> None:
    """A parked robot's refresh landing between glance and answer: the same view, so its maps fit."""
    answers, _, later = glanced_reusable(noisy(scene(), 4.0, 2))
    assert answers.put == [later] and answers.freed == [credits.UNCHANGED]


def test_newer_maps_of_another_view_do_not_answer_it_it_is_dropped_and_frees_the_slot() -> None:
    """A person walked in (the worker's frame) and out again (this frame): the person's maps would be sent
    under this frame's stamp. Counted, and the robot's slot freed (the newer maps went out)."""
    answers, stats, _ = glanced_reusable(with_person(scene()))
    assert answers.put == [] and answers.freed == [credits.SUPERSEDED]
    snapshot = stats.snapshot({})
    assert snapshot.dropped_by_reason.get(credits.SUPERSEDED) == 1
    assert snapshot.sources[SOURCE].unchanged == 0
