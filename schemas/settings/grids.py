"""Ground grid settings: one camera or several, intrinsics, mounts, layers (docs/grid.md)."""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from gcdtrav.schemas.strict import StrictModel
from numpy.typing import NDArray
from pydantic import Field, model_validator

# optical (x right, y down, z forward) -> body (x forward, y left, z up): the mount's convention, shared by the
# service's ground geometry and the viewer's camera transform.
OPTICAL_TO_BODY = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def rotation_rpy(roll: float, pitch: float, yaw: float) -> NDArray[np.float64]:
    """R = Rz(yaw) Ry(pitch) Rx(roll), the ROS convention (radians). Positive pitch tilts x down."""
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return np.asarray(rz @ ry @ rx, dtype=np.float64)


class CameraIntrinsics(StrictModel):
    """Pinhole intrinsics (pixels) for images of width x height; other image sizes are scaled."""

    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    width: int = Field(gt=0)
    height: int = Field(gt=0)


class CameraMountSettings(StrictModel):
    """The camera body frame (x forward, y left, z up) in the robot's base frame: metres and radians."""

    x: float = 0.0
    y: float = 0.0
    z: float = Field(default=1.0, description="Height above the ground plane z = 0.")
    roll: float = 0.0
    pitch: float = Field(default=0.0, description="Positive tilts the camera down.")
    yaw: float = 0.0


class GridCamera(StrictModel):
    """One camera of a grid: its source, intrinsics and where it sits on the robot."""

    source: str = Field(description="The source whose maps this camera's frames are, e.g. 'r1/front'.")
    intrinsics: CameraIntrinsics | None = None
    camera_info_key: str | None = Field(default=None, description="sensor_msgs/CameraInfo CDR key (overrides).")
    mount: CameraMountSettings = Field(default_factory=CameraMountSettings)
    depth_key: str | None = Field(default=None, description="Depth image (32FC1 m or 16UC1 mm, CDR) for 3-D points.")

    @model_validator(mode="after")
    def _needs_intrinsics(self) -> GridCamera:
        if self.intrinsics is None and self.camera_info_key is None:
            raise ValueError(f"camera '{self.source}': give intrinsics or a camera_info_key")
        return self


class PoseBufferSettings(StrictModel):
    """How a grid looks up the robot's pose at a frame's capture stamp (docs/grid.md, *Which pose*)."""

    span_s: float = Field(
        default=10.0,
        gt=0,
        description="Poses kept this long (by their stamps): a frame older than the oldest pose is not fused "
        "(before_poses); keep it above the slowest frame's capture-to-fusion time (max_frame_age_s).",
    )
    max_poses: int = Field(default=2000, ge=2, description="Poses kept at most (the oldest go first).")
    extrapolate_s: float = Field(
        default=0.1,
        ge=0,
        description="A frame up to this much newer than the newest pose (or older than the oldest) takes the "
        "pose extrapolated at the last velocity; beyond, the grid waits for the pose.",
    )
    wait_s: float = Field(
        default=0.2,
        ge=0,
        le=2.0,
        description="How long fusion waits for a pose stream that has not yet reached a frame's stamp; then "
        "the frame is not fused (pose_too_old). The worker waits, outside the grid's lock.",
    )
    max_gap_s: float = Field(
        default=0.5,
        gt=0,
        description="Two poses further apart are not interpolated between: a frame taken in the gap (the "
        "stream stopped) is not fused (pose_gap).",
    )


# The single-camera form's own fields: with ``cameras`` they belong to each camera instead.
SINGLE_CAMERA_FIELDS = ("intrinsics", "camera_info_key", "mount", "depth_key")


class GridSettings(StrictModel):
    """A ground grid around the robot, fed by one camera or several (see docs/grid.md).

    One camera: ``source`` with ``intrinsics`` or ``camera_info_key``, ``mount`` and ``depth_key``, as before.
    Several: ``cameras``, each with those fields; ``source`` then names the grid (default: the first camera's
    source). Either way the grid is published and queried under ``source``.
    """

    source: str = Field(
        default="",
        description="One camera: the source whose maps feed the grid, e.g. 'r1/front'. With cameras: the name "
        "the grid is published and queried under [default: the first camera's source].",
    )
    cameras: list[GridCamera] | None = Field(
        default=None, min_length=1, description="Several cameras fused into this grid (instead of the fields above)."
    )
    intrinsics: CameraIntrinsics | None = None
    camera_info_key: str | None = Field(default=None, description="sensor_msgs/CameraInfo CDR key (overrides).")
    mount: CameraMountSettings = Field(default_factory=CameraMountSettings)
    size_m: float = Field(default=20.0, gt=0)
    resolution_m: float = Field(default=0.1, gt=0)
    max_range_m: float = Field(default=10.0, gt=0, description="Ground points farther from the camera are dropped.")
    half_life_s: float = Field(default=2.0, gt=0, description="Old observations weigh half after this long.")
    max_age_s: float | None = Field(
        default=30.0,
        ge=0,
        description="A cell not observed for this long (by the frames' stamps) becomes unknown again, counted "
        "expired; 0 or null: never.",
    )
    pose_key: str | None = Field(default=None, description="Robot pose stream: the grid then lives in its frame.")
    pose_format: Literal["gcdtrav", "odometry"] = Field(
        default="gcdtrav", description="gcdtrav: msgpack Pose2D; odometry: nav_msgs/msg/Odometry CDR."
    )
    poses: PoseBufferSettings = Field(
        default_factory=PoseBufferSettings, description="The pose stream's buffer: each frame is fused at its pose."
    )
    depth_key: str | None = Field(default=None, description="Depth image (32FC1 m or 16UC1 mm, CDR) for 3-D points.")
    occupancy_grid: bool = Field(default=False, description="Also publish nav_msgs/OccupancyGrid CDR (T and U).")
    grid_map: bool = Field(default=False, description="Also publish grid_map_msgs/GridMap CDR with every layer.")
    costmap: bool = Field(default=False, description="Also publish a nav_msgs/OccupancyGrid costmap for Nav2.")
    lethal_tau: float = Field(
        default=0.1, ge=0, le=1, description="Costmap: a cell is lethal when P(T < lethal_tau) > lethal_probability."
    )
    lethal_probability: float = Field(default=0.25, ge=0, le=1, description="See lethal_tau.")
    min_match: float = Field(
        default=0.0,
        ge=0,
        le=1,
        description="Costmap: cells whose fused match score is below this are unknown (no anchor describes "
        "them); 0: never.",
    )

    @model_validator(mode="after")
    def _one_form(self) -> GridSettings:
        if self.cameras is not None:
            given = sorted(name for name in SINGLE_CAMERA_FIELDS if getattr(self, name) != _default(name))
            if given:
                raise ValueError(
                    f"grid '{self.source or self.cameras[0].source}': give either cameras or the single-camera "
                    f"fields, not both (move {', '.join(given)} into each camera)"
                )
            sources = [camera.source for camera in self.cameras]
            if len(set(sources)) != len(sources):
                raise ValueError(f"grid '{self.source or sources[0]}': a camera is listed twice in {sources}")
            self.source = self.source or sources[0]
        elif not self.source:
            raise ValueError("a grid needs a source (one camera) or cameras (several)")
        elif self.intrinsics is None and self.camera_info_key is None:
            raise ValueError(f"grid of '{self.source}': give intrinsics or a camera_info_key")
        if self.size_m / self.resolution_m > 2000:
            raise ValueError(f"grid of '{self.source}': more than 2000 x 2000 cells; coarsen resolution_m")
        return self

    def camera_list(self) -> list[GridCamera]:
        """The grid's cameras, the single-camera form as a list of one."""
        if self.cameras is not None:
            return self.cameras
        single = GridCamera(
            source=self.source,
            intrinsics=self.intrinsics,
            camera_info_key=self.camera_info_key,
            mount=self.mount,
            depth_key=self.depth_key,
        )
        return [single]


def _default(field: str) -> Any:
    """A GridSettings field's default (its dump holds the single-camera fields' defaults in either form)."""
    return GridSettings.model_fields[field].get_default(call_default_factory=True)


def one_grid_per_camera(grids: list[GridSettings]) -> None:
    names = [grid.source for grid in grids]
    if len(set(names)) != len(names):
        raise ValueError(f"two grids are published under the same source: {names}")
    cameras = [camera.source for grid in grids for camera in grid.camera_list()]
    if len(set(cameras)) != len(cameras):
        raise ValueError(f"a camera feeds two grids: {cameras}")
