"""How a ground grid is doing, for the service's status: frames fused and not fused by reason, the newest fused
stamp, the pose stream's age, the last costmap; a grid that fused nothing for a while is a problem.

Reasons a frame is not fused (``not_fused_by_reason``): ``no_intrinsics`` (no intrinsics configured and no
CameraInfo yet), ``no_mount`` (tf.mount: tf has not linked the base frame to the camera's frame yet), and those
of service/grid/poses.py: ``no_pose`` (the pose stream sent nothing yet),
``before_poses`` (the frame is older than the oldest pose held), ``pose_too_old`` (the newest pose is older
than the frame, beyond the extrapolation, after waiting), ``pose_gap`` (taken while the pose stream stopped).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from gcdtrav.service.grid.poses import AFTER_POSES, BEFORE_POSES, NO_POSE, POSE_GAP

NO_INTRINSICS = "no_intrinsics"
NO_MOUNT = "no_mount"  # tf.mount: the camera's transform from the base frame is not known yet
QUIET_S = 10.0  # a grid whose cameras send frames but that fused none for this long is a problem

# What each reason means, for the status's "why" section.
EXPLAINED = {
    NO_INTRINSICS: "no intrinsics (waiting for CameraInfo on camera_info_key)",
    NO_MOUNT: "no camera mount from tf yet: nothing links tf.base_frame to the camera's frame (the log says which)",
    NO_POSE: "no pose received on its pose stream yet",
    BEFORE_POSES: "frames older than every pose held (raise poses.span_s, or the pose stream restarted)",
    AFTER_POSES: "the pose stream lags or stopped: no pose at the frames' capture (poses.extrapolate_s, wait_s)",
    POSE_GAP: "frames taken while the pose stream was silent (poses.max_gap_s)",
}


@dataclass
class GridHealth:
    """Counters of one grid, written under its lock (``pose_received_at`` by ``add_pose`` and ``unchanged_at``
    by ``GridOutputs.unchanged`` without it: one assignment each, neither waits for a fusion)."""

    fused: int = 0
    not_fused: dict[str, int] = field(default_factory=dict)
    last_reason: dict[str, str] = field(default_factory=dict)  # camera -> why its last frame was not fused ("": it was)
    newest_fused_stamp: float | None = None
    fused_at: float | None = None  # service clock of the last fusion
    frame_at: float | None = None  # service clock of the last frame that reached the grid, fused or not
    pose_received_at: float | None = None  # service clock of the last pose
    costmap_at: float | None = None  # service clock of the last update that carried a costmap
    unchanged_at: float | None = None  # service clock of its cameras' last unchanged view (reused maps, not fused)

    def fused_frame(self, camera: str, stamp: float, now: float, costmap: bool) -> None:
        self.fused += 1
        self.last_reason[camera] = ""
        self.newest_fused_stamp = stamp if self.newest_fused_stamp is None else max(self.newest_fused_stamp, stamp)
        self.fused_at = self.frame_at = now
        if costmap:
            self.costmap_at = now

    def not_fused_frame(self, camera: str, reason: str, now: float) -> bool:
        """Count a frame not fused; True when it is the camera's first for this reason in a row (to log once)."""
        self.not_fused[reason] = self.not_fused.get(reason, 0) + 1
        self.frame_at = now
        new = self.last_reason.get(camera) != reason
        self.last_reason[camera] = reason
        return new

    def problem(self, now: float) -> str:
        """Why the grid fuses nothing: frames reach it, none fused for QUIET_S (or ever); '' when fine."""
        if self.frame_at is None or (self.fused_at is not None and now - self.fused_at < QUIET_S):
            return ""
        if self.fused_at is not None and self.frame_at <= self.fused_at:
            return ""  # no frames since the last fusion: the cameras are quiet, not the grid
        reasons = sorted({r for r in self.last_reason.values() if r}, key=lambda r: -self.not_fused.get(r, 0))
        if not reasons:
            return ""
        since = "fused no frame yet" if self.fused_at is None else f"fused no frame for {now - self.fused_at:.0f} s"
        return f"{since}: " + "; ".join(EXPLAINED.get(r, r) for r in reasons)
