"""Unchanged views are not inferred again (issue 34): the verdicts (``ReuseTracker``) and the glance thread
that applies them (``Triage``). No zenoh here: reused maps leave through ``republish``.

Each queued frame is looked at on the triage's own thread, so a parked robot's unchanged frames are answered
at their own rate while inference runs, and a change is known to the scheduler the moment its frame arrives.
Per source, every frame is glanced at (service/runtime/triage/change.py) and compared with the source's last
*inferred* frame (the reference: never with the last reused one, so a slow drift adds up until it counts).
The frame is **reused** (not inferred: that frame's maps are published again under this frame's stamp,
counted ``unchanged``) when all of these hold:

- reuse is enabled and the source has a reference (a frame inferred, its maps kept to publish) made with the
  active anchor set (after a swap every source's next frame is inferred);
- the frame has the reference's size (the maps' scale is for that size);
- at most ``changed_fraction`` of the thumbnail's blocks moved beyond ``block_threshold``;
- with a pose (a grid's pose stream), the robot neither moved ``translation_m`` nor turned ``rotation_deg``
  since the reference (turning in place in front of a blank wall counts as a change): both poses at their
  frames' capture stamps, not the newest when they reach the service (a frame is in flight for up to seconds:
  a robot that parks meanwhile did move between the two captures);
- the reference is younger than ``max_reuse_s``: after that the next frame is inferred, changed or not.
  While that refresh waits for its turn (it yields to frames with news up to the scheduler's floor,
  ``max_wait_s``), each later unchanged frame takes its place in line (the refresh infers a frame of now,
  not one that waited into staleness) and the frame it replaces is answered with the last maps; so up to
  ``max_reuse_s + 2 * max_wait_s``: the floor, then as long again for the frames overdue with it; a worker
  that long without serving is hung. Such a refresh frees the source's credit when it settles (``refresh``),
  so the robot's next unchanged frames are answered meanwhile.

Otherwise the frame goes to the scheduler with its claim (service/runtime/schedule/share.py): **refresh** when only
``max_reuse_s`` sent it; **urgent** when it changed after the view had settled (the frames before it
unchanged, reused or refreshed: its consumers hold maps of a view that is gone, a person walked in), which
the scheduler serves first within its limits; else **news**. A moving robot's views never settle, so its
frames are never urgent: its share is its weight's. The claim also carries the source's need: its motion
from the glances (the pose's speed where a pose is known, else the fraction of blocks that moved per second
between consecutive frames) and the ambiguity ahead in its last inferred maps.

A frame that cannot be glanced at (undecodable, a ROS message without a type) goes on to the worker, which
decodes it again and counts its fault by reason: one place counts bad frames.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from enum import Enum
from typing import NamedTuple

import numpy as np
from gcdtrav.schemas.messages import Pose2D, credits
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.schemas.settings.share import ReuseSettings, ScheduleSettings
from gcdtrav.service.runtime.frames import PendingFrame, ProcessedFrame
from gcdtrav.service.runtime.schedule.latest_queue import LatestFrameQueue
from gcdtrav.service.runtime.schedule.share import NO_NEED, Claim, FrameClass, Need, ambiguity_of
from gcdtrav.service.runtime.stats import ServiceStats
from gcdtrav.service.runtime.triage.change import (
    Glance,
    Thumbnail,
    glance,
    moved_fraction,
    pose_moved,
    pose_speeds,
    thumbnail_of_rgb,
)
from numpy.typing import NDArray

GLANCES_KEPT = 2
MOTION_TIME_CONSTANT_S = 1.0  # the motion estimate follows the glances with this time constant

UNCHANGED, CHANGED, POSE, FIRST, MAX_REUSE, OFF = "unchanged", "changed", "pose", "first", "max_reuse", "off"
ANCHORS, SIZE = "anchors", "size"


@dataclass(frozen=True)
class Verdict:
    reuse: bool
    reason: str  # UNCHANGED (reused), or why inferred: CHANGED, POSE, SIZE, ANCHORS, FIRST, MAX_REUSE, OFF
    moved: float  # fraction of blocks moved since the reference (1.0 without one)
    urgent: bool = False  # changed after the view had settled
    behind_refresh: bool = False  # reused past max_reuse_s because the source's refresh waits for its turn
    need: Need = NO_NEED  # the source's, as of this glance
    reference: int = 0  # which of the source's references it was judged against (ReuseTracker.fits)

    @property
    def claim(self) -> Claim | None:
        """The frame's claim on inference for the scheduler; None: reused."""
        if self.reuse:
            return None
        kind = FrameClass.REFRESH if self.reason == MAX_REUSE else FrameClass.NEWS
        return Claim(FrameClass.URGENT if self.urgent else kind, self.need)


@dataclass
class _View:
    reference: Thumbnail | None = None
    reference_pose: Pose2D | None = None
    reference_anchors: str = ""  # the anchor set version its maps were computed with
    reference_size: tuple[int, int] | None = None  # (width, height): the maps' scale is for this size
    references: int = 0  # references set so far: a verdict names the one it was judged against
    inferred_at: float = -math.inf
    settled: bool = False  # the last frame judged was unchanged (reused, or its refresh inferred)
    previous: Thumbnail | None = None
    previous_at: float = -math.inf
    previous_pose: Pose2D | None = None
    motion: float = 0.0  # 0..1
    ambiguity: float = 0.0  # 0..1, ahead in the reference's maps (service/runtime/schedule/share.py, ambiguity_of)
    # The last frames glanced at, for the reference: the one inferred is the newest ready one, maybe one
    # arrival behind the newest glance.
    glanced: deque[tuple[PendingFrame, Thumbnail]] = field(default_factory=lambda: deque(maxlen=GLANCES_KEPT))


# Where the robot carrying a source's camera was when a frame (capture stamp or None, receipt) was taken: the
# grids' GridOutputs.reuse_pose, the one capture-pose lookup fusion uses too.
PoseOf = Callable[[str, float | None, float], Pose2D | None]


class ReuseTracker:
    """Thread-safe: glances on the triage thread, references set by the worker's hand-off out (between keeping
    a frame's maps for reuse and putting them)."""

    def __init__(
        self,
        settings: ReuseSettings,
        schedule: ScheduleSettings | None = None,
        pose_of: PoseOf = lambda source, stamp, received_at: None,
        clock: Callable[[], float] = time.monotonic,
        anchors_version: Callable[[], str] = lambda: "",
    ) -> None:
        self.settings, self.schedule = settings, schedule or ScheduleSettings()
        self.pose_of, self.clock = pose_of, clock
        self.anchors_version = anchors_version  # the active set's: maps of another set are never reused
        self._refresh_limit_s = self.settings.max_reuse_s + 2 * self.schedule.max_wait_s
        self._views: dict[str, _View] = {}
        self._lock = threading.Lock()

    def judge(self, source: str, pending: PendingFrame, glance: Glance, refresh_waiting: bool = False) -> Verdict:
        """Reuse the source's last maps for this frame, or infer it (and how urgently). ``refresh_waiting``: a
        frame of the source already waits for inference; an unchanged view past ``max_reuse_s`` is then
        reused while that frame waits, instead of replacing it."""
        now, pose = self.clock(), self.pose_of(source, pending.stamp, pending.received_at)
        with self._lock:
            view = self._views.setdefault(source, _View())
            self._follow_motion(view, glance.thumbnail, pose, now)
            view.glanced.append((pending, glance.thumbnail))
            verdict = self._verdict(view, glance, pose, now, refresh_waiting)
            if verdict.reason in (UNCHANGED, MAX_REUSE, CHANGED, POSE, SIZE):
                view.settled = verdict.reason in (UNCHANGED, MAX_REUSE)
            return replace(verdict, need=Need(view.motion, view.ambiguity), reference=view.references)

    def fits(self, source: str, reference: int, pending: PendingFrame, glance: Glance) -> bool:
        """Whether a frame judged reusable against the source's reference number ``reference`` is still
        answered by the maps kept now: yes while that reference stands; after a newer one, only if the frame
        is unchanged against it too (a parked robot's refresh landing meanwhile: the same view)."""
        now, pose = self.clock(), self.pose_of(source, pending.stamp, pending.received_at)
        with self._lock:
            view = self._views.get(source)
            if view is None:
                return False
            return view.references == reference or self._verdict(view, glance, pose, now, False).reuse

    def _verdict(self, view: _View, glance: Glance, pose: Pose2D | None, now: float, refresh_waiting: bool) -> Verdict:
        if view.reference is None:
            return Verdict(False, FIRST, 1.0)
        if view.reference_anchors != self.anchors_version():
            return Verdict(False, ANCHORS, 1.0)
        if glance.size != view.reference_size:  # the maps' scale would not fit (e.g. a relay shrank the frames)
            return Verdict(False, SIZE, 1.0, urgent=view.settled)
        moved = moved_fraction(view.reference, glance.thumbnail, self.settings.block_threshold)
        changed = moved > self.settings.changed_fraction
        reference_pose = view.reference_pose
        # A pose known now but not at the reference: the maps were never placed there (the grid needs a frame).
        turned = pose is not None and (reference_pose is None or pose_moved(reference_pose, pose, self.settings))
        if changed or turned:
            return Verdict(False, CHANGED if changed else POSE, moved, urgent=view.settled)
        if not self.settings.enabled:
            return Verdict(False, OFF, moved)
        age = now - view.inferred_at
        # While a refresh waits its turn (yielding up to the scheduler's floor), the last maps still answer, up
        # to twice the floor: beyond it the worker is not serving (hung): frames then queue, the watchdog sees it.
        if age < self.settings.max_reuse_s:
            return Verdict(True, UNCHANGED, moved)
        if refresh_waiting and age < self._refresh_limit_s:
            return Verdict(True, UNCHANGED, moved, behind_refresh=True)
        return Verdict(False, MAX_REUSE, moved)

    def _follow_motion(self, view: _View, thumbnail: Thumbnail, pose: Pose2D | None, now: float) -> None:
        """The motion estimate: pose speed if known, else the image's change per second since the last glance."""
        dt = now - view.previous_at
        instant: float | None = None
        if pose is not None and view.previous_pose is not None:
            speeds = pose_speeds(view.previous_pose, pose)
            if speeds is not None:
                schedule = self.schedule
                instant = max(speeds[0] / schedule.full_speed_mps, speeds[1] / schedule.full_turn_dps)
        elif pose is None and view.previous is not None and 0 < dt < math.inf:
            moved = moved_fraction(view.previous, thumbnail, self.settings.block_threshold)
            instant = moved / dt / self.schedule.full_change_per_s
        if instant is not None:
            alpha = 1.0 - math.exp(-max(dt, 0.0) / MOTION_TIME_CONSTANT_S) if dt < math.inf else 1.0
            view.motion += alpha * (min(1.0, instant) - view.motion)
        view.previous, view.previous_at = thumbnail, now
        if pose is not None and (view.previous_pose is None or pose.stamp > view.previous_pose.stamp):
            view.previous_pose = pose

    def inferred(
        self, source: str, pending: PendingFrame, image: NDArray[np.uint8], anchors: str = "", ambiguity: float = 0.0
    ) -> None:
        """The source's frame was inferred (with the anchor set of version ``anchors``) and its maps kept for
        reuse (they go out next): the new reference, with its ``ambiguity`` ahead."""
        now, pose = self.clock(), self.pose_of(source, pending.stamp, pending.received_at)
        with self._lock:
            view = self._views.setdefault(source, _View())
            kept = next((thumbnail for frame, thumbnail in view.glanced if frame is pending), None)
            # Not glanced at (no triage for it, or its glance forgotten): from the decoded image, the same means.
            thumbnail = kept if kept is not None else thumbnail_of_rgb(image, self.settings.blocks)
            view.reference, view.reference_pose, view.inferred_at = thumbnail, pose, now
            view.references += 1
            view.reference_anchors, view.ambiguity = anchors, ambiguity
            view.reference_size = (int(image.shape[1]), int(image.shape[0]))

    def need(self, source: str) -> Need:
        with self._lock:
            view = self._views.get(source)
            return Need(view.motion, view.ambiguity) if view is not None else NO_NEED

    def forget(self, source: str) -> None:
        with self._lock:
            self._views.pop(source, None)


class Republished(Enum):
    """What became of an unchanged frame's answer."""

    PUT = "put"
    NOT_PUT = "not_put"  # closed (shutdown), or no maps of the source kept
    SUPERSEDED = "superseded"  # newer maps were kept since it was judged, and it does not match them


# The source's last maps under this frame, if the check (asked while the kept maps cannot change) says it fits them.
Republish = Callable[[PendingFrame, Glance, Callable[[], bool]], Republished]


class Reusable(NamedTuple):
    """A frame to answer with the source's last maps: its glance, and the reference it was judged against."""

    pending: PendingFrame
    seen: Glance
    reference: int


class Triage:
    """The glance thread's steps: each arrival judged, then settled in the queue (reused, or ready with its
    claim), reused frames answered, inferred frames made the new reference."""

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
        self.on_freed = on_freed  # the credits: the source may send its next frame (service/runtime/fleet/credits.py)

    def next_reusable(self, timeout: float) -> Reusable | None:
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
            self.frames.settle(source, pending, Claim(need=self.tracker.need(source)))
            return None
        verdict = self.tracker.judge(source, pending, seen, refresh_waiting=self.frames.has_ready(source))
        if verdict.claim is not None:
            if self.frames.settle(source, pending, verdict.claim) and verdict.reason == MAX_REUSE:
                self.on_freed(pending, credits.REFRESH)
            return None
        if verdict.behind_refresh:
            return self._in_line(source, pending, seen, verdict.reference)
        if not self.frames.settle(source, pending, None):
            return None  # replaced meanwhile: the newer frame is glanced at next
        return Reusable(pending, seen, verdict.reference)

    def _in_line(self, source: str, pending: PendingFrame, seen: Glance, reference: int) -> Reusable | None:
        """An unchanged frame while the source's refresh waits: it takes the refresh's place in line (so the
        refresh infers the newest view, never one that waited into staleness); the frame it replaced, older,
        is answered with the last maps instead."""
        answered = self.frames.settle_in_line(source, pending)
        if answered is None or answered is pending:
            return None if answered is None else Reusable(pending, seen, reference)
        settings = self.settings
        try:  # glanced once already: the same bytes give the same glance
            again = glance(answered, settings.max_payload_bytes, settings.max_pixels, settings.reuse.blocks)
            return Reusable(answered, again, reference)
        except Exception as err:  # counted, never the triage thread's end
            self.stats.rejected(source, "processing_failed", repr(err)[:200], err)
            return None

    def reuse(self, reusable: Reusable, map_age_s: float | None = None) -> None:
        """Publish the source's last maps for this frame and count it unchanged; ``map_age_s``: the frame's age
        as judged before publishing. Dropped instead at shutdown, or when newer maps it does not match were
        kept since it was judged (a frame is never answered with the maps of another view)."""
        pending, seen, reference = reusable
        source = pending.source
        answer = self.republish(pending, seen, lambda: self.tracker.fits(source, reference, pending, seen))
        if answer is Republished.PUT:
            self.stats.unchanged(source, map_age_s)
            self.on_freed(pending, credits.UNCHANGED)
        elif answer is Republished.SUPERSEDED:
            self.stats.dropped(source, credits.SUPERSEDED)
            self.on_freed(pending, credits.SUPERSEDED)
        else:
            self.stats.dropped(source, "shutdown")

    def inferred(self, done: ProcessedFrame) -> None:
        """A frame's maps are kept for reuse, about to go out: the source's new reference, with its ambiguity
        ahead for the scheduler (the hand-off out calls this between the two, runtime/outputs.py)."""
        maps = done.result.maps
        ambiguity = ambiguity_of(maps.uncertainty, maps.match, self.settings.schedule)
        self.tracker.inferred(done.source, done.pending, done.image.image, done.result.anchors.version, ambiguity)
