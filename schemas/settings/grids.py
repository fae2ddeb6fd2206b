"""Ground grid settings: one camera or several, intrinsics, mounts, layers (docs/grid.md)."""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from gcdtrav.schemas.limits import MAX_FRAME_ID_CHARS
from gcdtrav.schemas.strict import StrictModel
from numpy.typing import NDArray
from pydantic import Field, field_validator, model_validator

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


# tf2_msgs/msg/TFMessage as rmw_zenoh keys it: <domain>/<topic>/<type>/<type hash>, any domain and hash
TF_KEY = "*/tf/tf2_msgs::msg::dds_::TFMessage_/*"
TF_STATIC_KEY = "*/tf_static/tf2_msgs::msg::dds_::TFMessage_/*"
FRAME_AXES = Literal["auto", "optical", "body"]
# A camera's tf frame, in both forms (GridCamera and the single-camera GridSettings): one definition.
CAMERA_FRAME_ID: Any = Field(
    default=None,
    description="With tf.mount: the camera's tf frame [its images' header frame_id, else its CameraInfo's].",
)
CAMERA_FRAME_AXES: Any = Field(
    default="auto",
    description="With tf.mount: the camera frame's axes; optical: z forward, x right, y down; body: x forward, "
    "y left, z up; auto: optical when the frame's name holds 'optical' (ROS's *_optical_frame), else body.",
)


def _frame_name(value: str) -> str:
    if not value or len(value) > MAX_FRAME_ID_CHARS or value.startswith("/"):
        raise ValueError(f"'{value}' is not a tf frame id (1 to {MAX_FRAME_ID_CHARS} characters, no leading '/')")
    return value


class GridTfSettings(StrictModel):
    """The grid's geometry from ROS tf (/tf_static and /tf, tf2_msgs/TFMessage CDR; docs/grid.md, "Mount and
    pose from tf"): each camera's mount, the robot's pose, or both."""

    mount: bool = Field(
        default=False,
        description="Each camera's mount from tf: base_frame -> the camera's frame (its frame_id, else its images' "
        "header frame_id, else its CameraInfo's). Instead of mount:.",
    )
    pose: bool = Field(
        default=False, description="The robot's pose from tf: odom_frame -> base_frame. Instead of pose_key."
    )
    base_frame: str = Field(
        default="base_link",
        description="The robot frame whose z = 0 is the ground (the grid's ground plane): base_footprint on robots "
        "whose base_link sits above the ground.",
    )
    odom_frame: str = Field(
        default="odom", description="The grid's frame with pose: the pose is odom_frame -> base_frame."
    )
    tf_key: str = Field(
        default=TF_KEY, description="/tf's key: rmw_zenoh's (any domain and hash); 'tf' through zenoh-bridge-ros2dds."
    )
    tf_static_key: str = Field(
        default=TF_STATIC_KEY, description="/tf_static's key (transient local: read from the publishers' caches)."
    )
    buffer_s: float = Field(
        default=10.0, gt=0, le=300, description="How long /tf's transforms are kept for lookups (tf2's default)."
    )

    _frames = field_validator("base_frame", "odom_frame")(_frame_name)

    @model_validator(mode="after")
    def _something_from_tf(self) -> GridTfSettings:
        if not (self.mount or self.pose):
            raise ValueError("tf: set mount, pose or both to true (or leave tf out)")
        if self.base_frame == self.odom_frame:
            raise ValueError(f"tf: base_frame and odom_frame are both '{self.base_frame}'")
        return self


class GridCamera(StrictModel):
    """One camera of a grid: its source, intrinsics and where it sits on the robot."""

    source: str = Field(description="The source whose maps this camera's frames are, e.g. 'r1/front'.")
    intrinsics: CameraIntrinsics | None = None
    camera_info_key: str | None = Field(default=None, description="sensor_msgs/CameraInfo CDR key (overrides).")
    mount: CameraMountSettings = Field(default_factory=CameraMountSettings)
    depth_key: str | None = Field(default=None, description="Depth image (32FC1 m or 16UC1 mm, CDR) for 3-D points.")
    frame_id: str | None = CAMERA_FRAME_ID
    frame_axes: FRAME_AXES = CAMERA_FRAME_AXES

    _frame = field_validator("frame_id")(lambda value: value if value is None else _frame_name(value))

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


class GridSpeedSettings(StrictModel):
    """The speed layer: per cell, the fraction of the robot's maximum speed (docs/grid.md, "Speed from
    uncertainty"). Full speed where U and P(T < tau) are low; down to ``floor`` as either rises to its
    ``*_floor`` threshold (linearly between), where the match score is below ``min_match`` (novel ground) and,
    if ``unknown: floor``, where the grid knows nothing. Published as a Nav2 speed filter mask (percent of the
    maximum speed, 0 = no limit), its CostmapFilterInfo and a SpeedLimit at the robot's pose."""

    # 0.01: the mask's smallest limit is 1 percent (Nav2 reads a mask value 0 as "no limit")
    floor: float = Field(
        default=0.3, ge=0.01, le=1, description="The slowest fraction of maximum speed; 1: never slow."
    )
    u_full: float = Field(default=0.1, ge=0, le=1, description="U at or below this: no slowing for U.")
    u_floor: float = Field(default=0.2, ge=0, le=1, description="U at or above this: the floor.")
    p_below_full: float = Field(default=0.1, ge=0, le=1, description="P(T < tau) at or below this: no slowing.")
    p_below_floor: float = Field(default=0.5, ge=0, le=1, description="P(T < tau) at or above this: the floor.")
    min_match: float = Field(
        default=0.0, ge=0, le=1, description="Cells whose match score is below this are novel: the floor; 0: never."
    )
    lead_m: float = Field(
        default=0.5,
        ge=0,
        le=5,
        description="Slow ground reaches this far out (each cell takes the slowest within lead_m): Nav2's "
        "SpeedFilter reads only the robot's own cell, so the robot must start braking this far before ambiguous "
        "ground (its braking distance from full speed to the floor plus its speed times the filter's period).",
    )
    unknown: Literal["floor", "full"] = Field(
        default="floor", description="Cells never observed or expired: the floor, or full speed (no limit)."
    )
    rate_hz: float = Field(
        default=1.0,
        gt=0,
        le=10,
        description="At most this many masks a second (Nav2 logs a warning for every new mask); the SpeedLimit "
        "at the robot's pose goes out with every fused frame.",
    )
    stale_s: float = Field(
        default=3.0,
        gt=0,
        description="No frame fused and no view found unchanged (reused) for this long: the grid is stale and the "
        "safe mask (the floor everywhere) replaces the last one.",
    )

    @model_validator(mode="after")
    def _ramps_rise(self) -> GridSpeedSettings:
        for low, high in (("u_full", "u_floor"), ("p_below_full", "p_below_floor")):
            if getattr(self, low) >= getattr(self, high):
                raise ValueError(f"speed: {low} ({getattr(self, low)}) must be below {high} ({getattr(self, high)})")
        return self


# The single-camera form's own fields: with ``cameras`` they belong to each camera instead.
SINGLE_CAMERA_FIELDS = ("intrinsics", "camera_info_key", "mount", "depth_key", "frame_id", "frame_axes")


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
    tf: GridTfSettings | None = Field(
        default=None, description="The mounts, the pose or both from ROS tf instead of mount: and pose_key."
    )
    frame_id: str | None = CAMERA_FRAME_ID
    frame_axes: FRAME_AXES = CAMERA_FRAME_AXES
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

    speed: GridSpeedSettings | None = Field(
        default=None,
        description='Also publish a speed layer and Nav2 speed filter mask from U (docs/grid.md, "Speed from '
        'uncertainty"); null: off.',
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

    @model_validator(mode="after")
    def _geometry_from_one_place(self) -> GridSettings:
        """A mount or a pose given twice (in YAML and from tf) is an error, not a silent choice: which one the
        operator meant cannot be guessed, and a wrong mount misplaces every cell."""
        tf = self.tf
        if tf is not None and tf.pose and self.pose_key is not None:
            raise ValueError(f"grid '{self.source}': the pose comes from pose_key or from tf (tf.pose), not both")
        mount_from_tf = tf is not None and tf.mount
        for camera in self.camera_list():
            # judged by value, not by what the YAML spelt: a dumped config validates again unchanged
            if mount_from_tf and camera.mount != CameraMountSettings():
                raise ValueError(
                    f"grid '{self.source}', camera '{camera.source}': the mount comes from mount: or from tf "
                    "(tf.mount), not both"
                )
            if not mount_from_tf and (camera.frame_id is not None or camera.frame_axes != "auto"):
                raise ValueError(
                    f"grid '{self.source}', camera '{camera.source}': frame_id and frame_axes are read only with "
                    "tf: {mount: true}"
                )
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
            frame_id=self.frame_id,
            frame_axes=self.frame_axes,
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
