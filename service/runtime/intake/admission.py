"""What the subscriber callback checks before a frame takes any state, in order: the publisher's intake
rate (``admit``, service/runtime/intake/intake_rate.py: before anything of the sample is read, its key included),
then (``offer``) the source's name, for a new source the candidates' caps (service/runtime/intake/candidates.py),
the payload's size (refused unread: never copied out of the middleware's buffer), the frame's age (its
capture stamp, read without decoding by service/runtime/intake/frame_age.py, judged by
service/runtime/intake/freshness.py) and the pending frames' byte budget. No middleware here: the bus hands over
the publisher, the source, the size and a way to read.

A tracked source's frame that is refused frees its slot at once: ``on_freed`` (the credits) hears of it.

A new source is a candidate until the worker decodes one of its frames (``decoded``: it takes a slot of the
SourceTracker) or fails to (``undecodable``: forgotten at once, the frame counted rejected with its reason).
What is counted against a candidate is counted by reason only: invented names leave no per-source state."""

from __future__ import annotations

import time
from collections.abc import Callable

from gcdtrav.schemas.inputs import RejectedInput
from gcdtrav.schemas.limits import MAX_SOURCE_CHARS
from gcdtrav.schemas.messages.credits import REFUSED, STALE
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.ros.cdr import RosTopic
from gcdtrav.service.runtime.frames import FrameTimes, PendingFrame
from gcdtrav.service.runtime.intake.candidates import CandidatePool, over_publisher_cap
from gcdtrav.service.runtime.intake.frame_age import input_times
from gcdtrav.service.runtime.intake.freshness import Dropped, Freshness
from gcdtrav.service.runtime.intake.intake_rate import IntakeRate
from gcdtrav.service.runtime.intake.sources import SourcesFull, SourceTracker
from gcdtrav.service.runtime.schedule.latest_queue import LatestFrameQueue, PendingBudgetExceeded
from gcdtrav.service.runtime.stats import ServiceStats


class Admission:
    def __init__(
        self,
        settings: ServiceSettings,
        sources: SourceTracker,
        queue: LatestFrameQueue[PendingFrame],
        stats: ServiceStats,
        on_freed: Callable[[str, str, FrameTimes | None], None] = lambda source, reason, times: None,
        freshness: Freshness | None = None,
    ) -> None:
        self.settings, self.sources, self.queue, self.stats = settings, sources, queue, stats
        self.freshness = freshness or Freshness.from_settings(settings)
        self.on_freed = on_freed
        self.candidates = CandidatePool(settings.max_candidates)
        self.intake_rate = IntakeRate(
            settings.intake_rate_per_publisher, settings.intake_rate_anonymous, settings.intake_burst_s
        )

    def admit(self, publisher: str | None) -> bool:
        """The first check: the publisher is within its intake rate, checked before anything else of the
        sample is read; a refusal is counted by reason only (no source is known yet)."""
        if self.intake_rate.admit(publisher):
            return True
        self.stats.rejected_unread("rate_limited", lambda: f"publisher {publisher or '(no source info)'}")
        return False

    def offer(
        self,
        source: str,
        key: str,
        size: int,
        read: Callable[[], bytes],
        encoding: str,
        ros: RosTopic | None = None,
        publisher: str | None = None,
    ) -> bool:
        """Queue the frame as the source's newest, or count why not; True if queued."""
        if len(source) > MAX_SOURCE_CHARS:
            self.stats.rejected(
                None, "source_name_too_long", f"'{source[:60]}...' is over {MAX_SOURCE_CHARS} characters"
            )
            return False
        if self.sources.note(source):
            return self._offer_frame(source, key, size, read, encoding, ros, tracked=True)
        waiting = source in self.candidates
        if not waiting and not self._may_wait(source, publisher):
            return False
        queued = self._offer_frame(source, key, size, read, encoding, ros, tracked=False)
        if queued:
            self._forget_evicted(self.candidates.add(source, publisher))
        elif not waiting:
            self.sources.forget_untracked(source)  # the counters the refusal left
        return queued

    def _may_wait(self, source: str, publisher: str | None) -> bool:
        """A new source may wait as a candidate: a slot could be had and its publisher is under its cap."""
        if not self.sources.can_reclaim():
            self.stats.rejected(
                None, "too_many_sources", f"'{source[:200]}': already tracking {self.sources.max_sources} sources"
            )
            return False
        cap = self.settings.max_sources_per_publisher
        if publisher is not None and over_publisher_cap(publisher, self._of_publisher(publisher), cap):
            self.stats.rejected(None, "too_many_sources_per_publisher", f"'{source[:200]}': publisher has {cap}")
            return False
        return True

    def _of_publisher(self, publisher: str) -> int:
        return self.sources.of_publisher(publisher) + self.candidates.of_publisher(publisher)

    def _forget_evicted(self, evicted: str | None) -> None:
        if evicted is not None:
            self.sources.forget_untracked(evicted)  # its pending frame and counters
            self.stats.rejected(None, "candidate_evicted", f"'{evicted[:200]}': a newer new source took its place")

    def decoded(self, source: str) -> None:
        """One of ``source``'s frames decoded: a candidate takes a slot. Raises RejectedInput if none is left."""
        _, publisher = self.candidates.pop(source)
        try:
            self.sources.promote(source, publisher)
        except SourcesFull as err:
            self.sources.forget_untracked(source)
            raise RejectedInput("too_many_sources", str(err)) from None

    def taken(self, source: str) -> None:
        """The worker took a frame of ``source``: a candidate's is no longer evictable."""
        self.candidates.take(source)

    def undecodable(self, source: str) -> bool:
        """One of ``source``'s frames failed: a candidate is forgotten at once. False if the frame was already
        counted (its candidate evicted between the queue and ``taken``): not to be counted again."""
        was_candidate, _ = self.candidates.pop(source)
        self.sources.forget_untracked(source)  # also what taking an evicted candidate's frame left (credits)
        return was_candidate or source in self.sources

    def _offer_frame(
        self,
        source: str,
        key: str,
        size: int,
        read: Callable[[], bytes],
        encoding: str,
        ros: RosTopic | None,
        tracked: bool,
    ) -> bool:
        received_at = time.time()
        if size > self.settings.max_payload_bytes:
            self.queue.count_unqueued(source)
            self.stats.intake(source, size, None)
            self.stats.rejected(
                source, "oversized", f"{size} bytes exceeds the limit of {self.settings.max_payload_bytes}"
            )
            self.on_freed(source, REFUSED, FrameTimes(None, None, received_at))
            return False
        payload = read()
        times = input_times(payload, encoding, ros is not None)
        age = self.freshness.at_intake(source, times.stamp, received_at)
        self.stats.intake(source, size, age.lag_s)
        frame_times = FrameTimes(times.stamp, times.sent_at, received_at)
        if age.refusal is not None:
            self.queue.count_unqueued(source)
            if isinstance(age.refusal, Dropped):
                self.stats.stale(source, age.refusal.detail)
            else:
                self.stats.rejected(source, age.refusal.reason, age.refusal.detail, tracked=tracked)
            self.on_freed(source, STALE if isinstance(age.refusal, Dropped) else REFUSED, frame_times)
            return False
        pending = PendingFrame(source, key, payload, encoding, received_at, ros, times.stamp, times.sent_at, age.lag_s)
        try:
            self.queue.put(source, pending, size)
        except PendingBudgetExceeded as err:
            self.stats.rejected(source, "pending_budget", str(err))
            self.on_freed(source, REFUSED, frame_times)
            return False
        return True
