"""The glance before inference (issue 34): each queued frame is looked at on its own thread, so a parked
robot's unchanged frames are answered at their own rate while inference runs, and a change is known to the
scheduler the moment its frame arrives. No zenoh here: reused maps leave through ``republish``.

A frame that cannot be glanced at (undecodable, a ROS message without a type) goes on to the worker, which
decodes it again and counts its fault by reason: one place counts bad frames.
"""

from __future__ import annotations

from collections.abc import Callable

from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.runtime.change import Glance, glance
from gcdtrav.service.runtime.credits import REFRESH, UNCHANGED
from gcdtrav.service.runtime.frames import PendingFrame, ProcessedFrame
from gcdtrav.service.runtime.latest_queue import LatestFrameQueue
from gcdtrav.service.runtime.reuse import MAX_REUSE, ReuseTracker
from gcdtrav.service.runtime.share import SharePolicy, ambiguity_of
from gcdtrav.service.runtime.stats import ServiceStats

Republish = Callable[[PendingFrame, Glance], bool]  # the source's last maps under this frame; False: not put


class Triage:
    def __init__(
        self,
        frames: LatestFrameQueue[PendingFrame],
        tracker: ReuseTracker,
        settings: ServiceSettings,
        stats: ServiceStats,
        republish: Republish,
        on_freed: Callable[[PendingFrame, str], None] = lambda pending, reason: None,
    ) -> None:
        self.frames, self.tracker, self.settings, self.stats = frames, tracker, settings, stats
        self.republish = republish
        self.on_freed = on_freed  # the credits: the source may send its next frame (service/runtime/credits.py)

    @property
    def policy(self) -> SharePolicy:
        return self.frames.policy

    def next_reusable(self, timeout: float) -> tuple[PendingFrame, Glance] | None:
        """Glance at the next queued frame; the frame and its glance if it is to be reused (it has left the
        queue), None if it went on to inference (or nothing came within ``timeout``)."""
        item = self.frames.take_untriaged(timeout)
        if item is None:
            return None
        source, pending = item
        settings = self.settings
        try:
            seen = glance(pending, settings.max_payload_bytes, settings.max_pixels, settings.reuse.blocks)
        except Exception:  # the worker decodes it again and counts why it failed
            self.frames.settle(source, pending, reused=False)
            return None
        verdict = self.tracker.judge(source, pending, seen, refresh_waiting=self.frames.has_ready(source))
        if not verdict.reuse:
            self.policy.mark_refresh(source, verdict.reason == MAX_REUSE)
            if verdict.urgent:
                self.policy.mark_urgent(source)
            if self.frames.settle(source, pending, reused=False) and verdict.reason == MAX_REUSE:
                self.on_freed(pending, REFRESH)
            return None
        if verdict.behind_refresh:
            return self._in_line(source, pending, seen)
        if not self.frames.settle(source, pending, reused=True):
            return None  # replaced meanwhile: the newer frame is glanced at next
        return pending, seen

    def _in_line(self, source: str, pending: PendingFrame, seen: Glance) -> tuple[PendingFrame, Glance] | None:
        """An unchanged frame while the source's refresh waits: it takes the refresh's place in line (so the
        refresh infers the newest view, never one that waited into staleness); the frame it replaced, older,
        is answered with the last maps instead."""
        answered = self.frames.settle_in_line(source, pending)
        if answered is None or answered is pending:
            return None if answered is None else (pending, seen)
        settings = self.settings
        try:  # glanced once already: the same bytes give the same glance
            return answered, glance(answered, settings.max_payload_bytes, settings.max_pixels, settings.reuse.blocks)
        except Exception as err:  # counted, never the triage thread's end
            self.stats.rejected(source, "processing_failed", repr(err)[:200], err)
            return None

    def reuse(self, pending: PendingFrame, seen: Glance, map_age_s: float | None = None) -> None:
        """Publish the source's last maps for this frame and count it unchanged (a shutdown's: dropped);
        ``map_age_s``: the frame's age as judged before publishing."""
        if not self.republish(pending, seen):
            self.stats.dropped(pending.source, "shutdown")
            return
        self.stats.unchanged(pending.source, map_age_s)
        self.on_freed(pending, UNCHANGED)

    def inferred(self, done: ProcessedFrame) -> None:
        """A frame's maps went out: the source's new reference, and its ambiguity ahead for the scheduler."""
        self.tracker.inferred(done.source, done.pending, done.image.image, done.result.anchors.version)
        maps = done.result.maps
        self.policy.set_ambiguity(done.source, ambiguity_of(maps.uncertainty, maps.match, self.settings.schedule))
