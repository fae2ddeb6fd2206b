"""Unchanged views are not inferred again (issue 34). No zenoh here.

Per source, every frame is glanced at (service/runtime/change.py) and compared with the source's last
*inferred* frame (the reference: never with the last reused one, so a slow drift adds up until it counts).
The frame is **reused** (not inferred: that frame's maps are published again under this frame's stamp,
counted ``unchanged``) when all of these hold:

- reuse is enabled and the source has a reference (a frame inferred and published);
- at most ``changed_fraction`` of the thumbnail's blocks moved beyond ``block_threshold``;
- with a pose (a grid's pose stream), the robot neither moved ``translation_m`` nor turned ``rotation_deg``
  since the reference (turning in place in front of a blank wall counts as a change);
- the reference is younger than ``max_reuse_s``: after that the next frame is inferred, changed or not.

Otherwise the frame goes to the scheduler; **urgent** when it changed while the source's consumers hold
reused maps (they show a view that is gone: a person walked in), which the scheduler serves first within
its limits (service/runtime/share.py). The glances also give the scheduler each source's motion: the pose's
speed where a pose is known, else the fraction of blocks that moved per second between consecutive frames.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from gcdtrav.schemas.compute_share import ReuseSettings, ScheduleSettings
from gcdtrav.schemas.messages import Pose2D
from gcdtrav.service.runtime.change import (
    Glance,
    Thumbnail,
    moved_fraction,
    pose_moved,
    pose_speeds,
    thumbnail_of_rgb,
)
from gcdtrav.service.runtime.frames import PendingFrame
from numpy.typing import NDArray

GLANCES_KEPT = 2
MOTION_TIME_CONSTANT_S = 1.0  # the motion estimate follows the glances with this time constant

UNCHANGED, CHANGED, POSE, FIRST, MAX_REUSE, OFF = "unchanged", "changed", "pose", "first", "max_reuse", "off"


@dataclass(frozen=True)
class Verdict:
    reuse: bool
    reason: str  # UNCHANGED (reused), or why inferred: CHANGED, POSE, FIRST, MAX_REUSE, OFF
    moved: float  # fraction of blocks moved since the reference (1.0 without one)
    urgent: bool = False  # changed while the source's consumers hold reused maps


@dataclass
class _View:
    reference: Thumbnail | None = None
    reference_pose: Pose2D | None = None
    inferred_at: float = -math.inf
    reusing: bool = False  # the source's last published maps were reused
    previous: Thumbnail | None = None
    previous_at: float = -math.inf
    previous_pose: Pose2D | None = None
    motion: float = 0.0  # 0..1
    # The last frames glanced at, for the reference: the one inferred is the newest ready one, maybe one
    # arrival behind the newest glance.
    glanced: deque[tuple[PendingFrame, Thumbnail]] = field(default_factory=lambda: deque(maxlen=GLANCES_KEPT))


class ReuseTracker:
    """Thread-safe: glances on the triage thread, references set by the worker after publishing."""

    def __init__(
        self,
        settings: ReuseSettings,
        schedule: ScheduleSettings | None = None,
        pose_of: Callable[[str], Pose2D | None] = lambda source: None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.settings, self.schedule = settings, schedule or ScheduleSettings()
        self.pose_of, self.clock = pose_of, clock
        self._views: dict[str, _View] = {}
        self._lock = threading.Lock()

    def judge(self, source: str, pending: PendingFrame, glance: Glance, refresh_waiting: bool = False) -> Verdict:
        """Reuse the source's last maps for this frame, or infer it (and how urgently). ``refresh_waiting``: a
        frame of the source already waits for inference; an unchanged view past ``max_reuse_s`` is then
        reused while that frame waits, instead of replacing it."""
        now, pose = self.clock(), self.pose_of(source)
        with self._lock:
            view = self._views.setdefault(source, _View())
            self._follow_motion(view, glance.thumbnail, pose, now)
            view.glanced.append((pending, glance.thumbnail))
            verdict = self._verdict(view, glance.thumbnail, pose, now, refresh_waiting)
            if verdict.reuse:
                view.reusing = True
            return verdict

    def _verdict(
        self, view: _View, thumbnail: Thumbnail, pose: Pose2D | None, now: float, refresh_waiting: bool
    ) -> Verdict:
        if view.reference is None:
            return Verdict(False, FIRST, 1.0)
        moved = moved_fraction(view.reference, thumbnail, self.settings.block_threshold)
        changed = moved > self.settings.changed_fraction
        reference_pose = view.reference_pose
        turned = pose is not None and reference_pose is not None and pose_moved(reference_pose, pose, self.settings)
        if changed or turned:
            return Verdict(False, CHANGED if changed else POSE, moved, urgent=view.reusing)
        if not self.settings.enabled:
            return Verdict(False, OFF, moved)
        if now - view.inferred_at >= self.settings.max_reuse_s and not refresh_waiting:
            return Verdict(False, MAX_REUSE, moved)
        return Verdict(True, UNCHANGED, moved)

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

    def inferred(self, source: str, pending: PendingFrame, image: NDArray[np.uint8]) -> None:
        """The source's frame was inferred and its maps published: the new reference."""
        now, pose = self.clock(), self.pose_of(source)
        with self._lock:
            view = self._views.setdefault(source, _View())
            kept = next((thumbnail for frame, thumbnail in view.glanced if frame is pending), None)
            # Not glanced at (no triage for it, or its glance forgotten): from the decoded image, the same means.
            thumbnail = kept if kept is not None else thumbnail_of_rgb(image, self.settings.blocks)
            view.reference, view.reference_pose, view.inferred_at = thumbnail, pose, now
            view.reusing = False

    def motion(self, source: str) -> float:
        with self._lock:
            view = self._views.get(source)
            return view.motion if view is not None else 0.0

    def forget(self, source: str) -> None:
        with self._lock:
            self._views.pop(source, None)
