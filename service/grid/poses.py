"""The robot's recent poses, to look one up at a frame's capture stamp (docs/grid.md, *Which pose*). No middleware.

A frame reaches fusion 0.5-2 s after it was taken (link, queue, inference); projected with the latest pose,
its ground lands speed x latency too far ahead. ``PoseBuffer`` keeps one pose stream's poses of the last
``span_s`` (at most ``max_poses``), ordered by stamp, and answers the pose at any stamp among them:

- between two poses: interpolated, position linearly, heading along the shortest arc;
- within ``extrapolate_s`` after the newest pose: extrapolated at the last two poses' velocity (held, with
  one pose or when those two are over ``max_gap_s`` apart); later: none yet (``AFTER_POSES``: the caller may
  ``wait`` a bounded time for the stream to catch up);
- within ``extrapolate_s`` before the oldest pose: the oldest; earlier: none (``BEFORE_POSES``, the frame is
  older than the buffer);
- inside a gap of more than ``max_gap_s`` between two poses (the stream stopped, then resumed): as beyond
  the poses on either side (within ``extrapolate_s`` of one), else none (``POSE_GAP``): where the robot went
  meanwhile is unknown.

Poses out of order take their place by stamp; a pose of the same stamp replaces the one held. A pose older
than the newest by more than ``span_s`` means the stream's clock stepped back (a bag replayed from its
start, a simulator reset): the buffer restarts from it. So does a pose in another frame than the buffer's
(the odometry frame changed; poses of two frames do not interpolate). Stamps are the pose stream's clock,
which the lookups assume is the frames' (both the robot's, docs/grid.md). With each pose's receipt on the
service's clock, ``offset_s`` is the stream's clock learnt as a source's is (the one smallest-delay window,
schemas/delay_window.py): the clock offset plus the link's smallest delay; a restart learns it afresh.
"""

from __future__ import annotations

import bisect
import math
import threading
from dataclasses import dataclass

from gcdtrav.schemas.delay_window import SmallestDelay
from gcdtrav.schemas.messages import Pose2D

# Why a stamp has no pose (also the grid's counters of frames not fused: service/runtime/grids).
NO_POSE, BEFORE_POSES, AFTER_POSES, POSE_GAP = "no_pose", "before_poses", "pose_too_old", "pose_gap"


@dataclass(frozen=True)
class PoseAt:
    """The answer to a lookup: the pose, or why there is none; ``extrapolated_s``: how far beyond the poses
    it was extrapolated (0: interpolated or exact)."""

    pose: Pose2D | None
    reason: str | None = None
    extrapolated_s: float = 0.0


def wrap_angle(angle: float) -> float:
    """The angle in [-pi, pi)."""
    return (angle + math.pi) % (2 * math.pi) - math.pi


def interpolate(a: Pose2D, b: Pose2D, stamp: float) -> Pose2D:
    """The pose at ``stamp`` on the line from ``a`` to ``b`` (a fraction outside [0, 1] extrapolates);
    the heading turns along the shortest arc."""
    span = b.stamp - a.stamp
    f = (stamp - a.stamp) / span if span > 0 else 1.0
    yaw = wrap_angle(a.yaw + f * wrap_angle(b.yaw - a.yaw))
    x, y = a.x + f * (b.x - a.x), a.y + f * (b.y - a.y)
    return Pose2D.model_construct(stamp=stamp, frame_id=b.frame_id, x=x, y=y, yaw=yaw)


class PoseBuffer:
    """One pose stream's recent poses; thread-safe (the pose subscriber adds, the worker looks up)."""

    def __init__(self, span_s: float, max_poses: int, extrapolate_s: float, max_gap_s: float) -> None:
        self.span_s, self.max_poses, self.extrapolate_s, self.max_gap_s = span_s, max_poses, extrapolate_s, max_gap_s
        self._poses: list[Pose2D] = []
        self._stamps: list[float] = []
        self._delays = SmallestDelay()  # receipt minus stamp of the poses received (receipt known)
        self._changed = threading.Condition()
        self.received = self.out_of_order = self.restarts = 0

    def add(self, pose: Pose2D, received_at: float | None = None) -> None:
        """Hold a pose (received at ``received_at`` on the service's clock, if known); wakes the lookups
        waiting for it."""
        with self._changed:
            self.received += 1
            stepped_back = bool(self._stamps) and pose.stamp < self._stamps[-1] - self.span_s
            if stepped_back or (bool(self._poses) and pose.frame_id != self._poses[-1].frame_id):
                self.restarts += 1  # the frame changed, or the clock stepped back: the old poses mean nothing now
                self._poses, self._stamps, self._delays = [], [], SmallestDelay()
            if received_at is not None:
                self._delays.add(received_at, received_at - pose.stamp)
            at = bisect.bisect_left(self._stamps, pose.stamp)
            if at < len(self._stamps) and self._stamps[at] == pose.stamp:
                self._poses[at] = pose
            else:
                self.out_of_order += at < len(self._stamps)
                self._poses.insert(at, pose)
                self._stamps.insert(at, pose.stamp)
            self._trim()
            self._changed.notify_all()

    def _trim(self) -> None:
        oldest = self._stamps[-1] - self.span_s
        drop = max(bisect.bisect_left(self._stamps, oldest), len(self._stamps) - self.max_poses)
        if drop > 0:
            del self._poses[:drop], self._stamps[:drop]

    @property
    def offset_s(self) -> float | None:
        """The stream's clock: service minus pose clock plus the link's smallest delay; None without a pose
        whose receipt is known."""
        with self._changed:
            return self._delays.smallest

    @property
    def newest(self) -> Pose2D | None:
        """The pose of the newest stamp held."""
        with self._changed:
            return self._poses[-1] if self._poses else None

    def __len__(self) -> int:
        with self._changed:
            return len(self._poses)

    def at(self, stamp: float) -> PoseAt:
        """The pose at ``stamp`` (see the module's rules)."""
        with self._changed:
            return self._at(stamp)

    def wait(self, stamp: float, timeout_s: float) -> PoseAt:
        """The pose at ``stamp``, waiting up to ``timeout_s`` while the stream has not reached it yet
        (``AFTER_POSES``); never holds anything but the buffer's own lock, released while waiting."""
        with self._changed:
            found = self._at(stamp)
            if found.reason == AFTER_POSES and timeout_s > 0:
                self._changed.wait_for(lambda: self._at(stamp).reason != AFTER_POSES, timeout_s)
                found = self._at(stamp)
            return found

    def _at(self, stamp: float) -> PoseAt:
        poses, stamps = self._poses, self._stamps
        if not poses:
            return PoseAt(None, NO_POSE)
        at = bisect.bisect_left(stamps, stamp)
        if at < len(stamps) and stamps[at] == stamp:
            return PoseAt(poses[at])
        if at == 0:
            if stamps[0] - stamp > self.extrapolate_s:
                return PoseAt(None, BEFORE_POSES)
            return PoseAt(interpolate(poses[0], poses[0], stamp), extrapolated_s=stamps[0] - stamp)
        if at == len(stamps):
            ahead = stamp - stamps[-1]
            return self._after(len(stamps) - 1, stamp) if ahead <= self.extrapolate_s else PoseAt(None, AFTER_POSES)
        if stamps[at] - stamps[at - 1] <= self.max_gap_s:
            return PoseAt(interpolate(poses[at - 1], poses[at], stamp))
        # in a gap: as if the later poses had not come yet (or the earlier ones were gone), else none
        if stamp - stamps[at - 1] <= self.extrapolate_s:
            return self._after(at - 1, stamp)
        if stamps[at] - stamp <= self.extrapolate_s:
            return PoseAt(interpolate(poses[at], poses[at], stamp), extrapolated_s=stamps[at] - stamp)
        return PoseAt(None, POSE_GAP)

    def _after(self, last: int, stamp: float) -> PoseAt:
        """Extrapolated from pose ``last`` at the velocity since the one before (held across a gap)."""
        poses = self._poses
        before = poses[last - 1] if last > 0 and poses[last].stamp - poses[last - 1].stamp <= self.max_gap_s else None
        return PoseAt(interpolate(before or poses[last], poses[last], stamp), extrapolated_s=stamp - poses[last].stamp)
