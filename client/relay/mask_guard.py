"""The robot's own judgement of the speed mask in force: when the service goes quiet, the safe mask (no zenoh,
no ROS, a clock given; docs/ros2.md, "When the link dies").

Nav2 never checks a mask's age, and a killed, frozen or cut-off service can send no safe mask of its own: the
last live mask would stay in force, and SpeedFilter gives no limit at all once the robot drives off it. So the
relay, on the robot, watches each source by its own monotonic clock:

- **silence**: nothing from the service about the source (a mask, a costmap, a speed limit, maps, a credit)
  for ``after_s``: the service can no longer replace its own mask (it does so itself while it reaches the
  robot, when its grid goes stale or it stops). The guard hands out the **safe mask**: the floor everywhere,
  in the frame of the robot's odometry (else the last live mask's), centred on the robot's newest pose and
  ``2 x max_speed x horizon`` across each way, so that the robot cannot drive off it before an operator can act;
  it is handed out again, re-centred, once the robot has come halfway to its rim.
- **a late mask**: a live mask whose capture stamp is more than ``after_s`` old when it arrives (a backlog
  flushed after an outage, a frozen service resumed, a service too slow for ``after_s``) is not put in force,
  and the mask in force, older still, gives way to the safe mask at once. The next fresh mask takes over at
  once. Evidence counts every message of the source, at the camera's rate, not only masks at their
  rate: the silence that turns the mask safe is the link's, so the boundary does not flap with mask timing.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from gcdtrav.schemas.relay import SafeMaskSettings
from gcdtrav.schemas.ros_nav import GridGeometry, occupancy_grid_cdr, speed_mask_values
from numpy.typing import NDArray

LIVE, SAFE, WAITING = "live", "safe", "waiting"  # WAITING: no live mask yet, and the service not quiet yet


@dataclass(frozen=True)
class Pose:
    x: float
    y: float
    frame_id: str


@dataclass(frozen=True)
class SafeMask:
    """The safe mask to hand out: a square of ``cells`` x ``cells`` at the floor's percent."""

    source: str
    frame_id: str
    resolution: float
    cells: int
    origin: tuple[float, float]  # the corner of cell (0, 0)
    percent: int
    reason: str

    @property
    def centre(self) -> tuple[float, float]:
        half = self.cells * self.resolution / 2
        return self.origin[0] + half, self.origin[1] + half

    def values(self) -> NDArray[np.int8]:
        return np.full((self.cells, self.cells), self.percent, np.int8)

    def cdr(self, stamp: tuple[int, int]) -> bytes:
        """The mask as a nav_msgs/OccupancyGrid's CDR, stamped (sec, nanosec)."""
        return occupancy_grid_cdr(stamp, self.frame_id, self.resolution, self.origin, self.values())


def floor_percent(floor: float) -> int:
    """The floor as a mask value, as the service writes it: 1..99, 0 for "no limit"."""
    return int(speed_mask_values(np.array(floor))[()])


class MaskGuard:
    """One source's guard; thread-safe (zenoh's and rclpy's callbacks feed it, the relay's thread asks ``due``)."""

    def __init__(self, source: str, settings: SafeMaskSettings, clock: Callable[[], float] = time.monotonic) -> None:
        self.source, self.settings, self._clock = source, settings, clock
        self._heard_at = clock()  # from the start: a service never heard turns the mask safe after after_s
        self._heard_ever = False
        self._live_frame: GridGeometry | None = None
        self._pose: Pose | None = None
        self._handed: SafeMask | None = None  # the safe mask in force, if one is
        self._late: str | None = None  # why a late mask turns the mask safe before any silence
        self.state = WAITING
        self.reason: str | None = None
        self.late_masks = 0  # live masks not put in force: older than after_s when they arrived
        self.safe_masks = 0
        self._lock = threading.Lock()
        # Held by whoever decides on a mask and puts it on the robot's side (a live mask's delivery, a safe mask's
        # put), so the two happen as one step: a safe mask decided just before a fresh live mask arrives is never
        # put after it (the robot would stay at the floor under a guard that says live).
        self.turn = threading.Lock()

    # ---- what the relay sees -----------------------------------------------------------------------
    def heard(self) -> None:
        """Any message of the service about this source arrived."""
        with self._lock:
            self._heard_at, self._heard_ever = self._clock(), True

    def pose(self, x: float, y: float, frame_id: str) -> None:
        """The robot's newest pose (its odometry, full rate)."""
        if math.isfinite(x) and math.isfinite(y):
            self._pose = Pose(x, y, frame_id)  # one reference, swapped whole

    def live_mask(self, geometry: GridGeometry, age_s: float | None) -> bool:
        """A live mask arrived, captured ``age_s`` ago on this host's clock (None: unknown, taken as fresh).
        Whether to put it in force: not when it is older than ``after_s`` (it is counted instead)."""
        with self._lock:
            self._heard_at, self._heard_ever = self._clock(), True
            if age_s is not None and age_s > self.settings.after_s:
                self.late_masks += 1
                if self.state != SAFE:
                    after, source = self.settings.after_s, self.source
                    self._late = f"a mask of {source} came {age_s:.1f} s after its capture (safe after {after:g} s)"
                return False
            self._live_frame, self._handed, self._late = geometry, None, None
            self.state, self.reason = LIVE, None
            return True

    # ---- what the relay hands out ------------------------------------------------------------------
    def due(self) -> SafeMask | None:
        """The safe mask to hand out now: the first of a silence, or a re-centred one; None otherwise."""
        with self._lock:
            quiet_s = self._clock() - self._heard_at
            quiet = quiet_s > self.settings.after_s
            handed, pose = self._handed, self._pose
            if handed is None:
                if self._late is None and not quiet:
                    return None
            elif pose is None or not self._near_rim(handed, pose):
                return None
            # A safe mask in force is re-centred whatever keeps it in force: silence, or a service still heard
            # whose masks all come late (the robot drives on under the floor either way).
            heard = "nothing" if not self._heard_ever else "no message"
            silence = f"{heard} from the service about {self.source} for {quiet_s:.1f} s"
            reason = self._late or (f"{silence} (safe after {self.settings.after_s:g} s)" if quiet else self.reason)
            assert reason is not None  # a safe mask in force has its reason
            mask = self._safe_mask(reason)
            if mask is None:
                self.reason = f"{reason}; no safe mask: neither a pose nor a live mask gives its frame"
                return None
            self._handed, self._late, self.state, self.reason = mask, None, SAFE, reason
            self.safe_masks += 1
            return mask

    def _near_rim(self, mask: SafeMask, pose: Pose) -> bool:
        """Whether the robot has come halfway from the safe mask's centre to its rim (or changed frame)."""
        if pose.frame_id != mask.frame_id:
            return True
        centre = mask.centre
        half = mask.cells * mask.resolution / 2
        return max(abs(pose.x - centre[0]), abs(pose.y - centre[1])) > half / 2

    def _safe_mask(self, reason: str) -> SafeMask | None:
        """Centred on the robot, else on the last live mask; None when neither is known (no frame to put it in)."""
        settings, pose, live = self.settings, self._pose, self._live_frame
        if pose is not None:
            frame_id, centre = pose.frame_id or (live.frame_id if live else ""), (pose.x, pose.y)
        elif live is not None:
            frame_id = live.frame_id
            centre = (
                live.origin[0] + live.width * live.resolution / 2,
                live.origin[1] + live.height * live.resolution / 2,
            )
        else:
            return None
        reach = 2 * settings.max_speed_m_s * settings.horizon_s
        cells = max(1, math.ceil(2 * reach / settings.resolution_m))
        half = cells * settings.resolution_m / 2
        origin = (centre[0] - half, centre[1] - half)
        return SafeMask(
            self.source, frame_id, settings.resolution_m, cells, origin, floor_percent(settings.floor), reason
        )
