"""Settings of `gcdtrav relay`, the robot side of a slow link: strict, like every configuration.

One relay serves every camera of a robot. Each camera is a zenoh key of images (JPEG, PNG or ImageEnvelope)
or a ROS 2 topic on the robot's own zenoh router (rmw_zenoh, or zenoh-bridge-ros2dds), and becomes one
source of the service.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Literal

from gcdtrav.schemas.settings.experience import TrackingSettings
from gcdtrav.schemas.strict import StrictModel, problems
from gcdtrav.schemas.yaml_file import load_mapping
from pydantic import Field, ValidationError, field_validator, model_validator

Output = Literal["maps", "maps8", "grid", "preview", "speed_mask", "costmap", "nav2_costmap"]
# speed_mask, costmap (nav_msgs/OccupancyGrid) and nav2_costmap (nav2_msgs/Costmap): the grid's CDRs, under
# {prefix}/out/{source}/grid/{kind}
FORWARDABLE: tuple[Output, ...] = ("maps", "maps8", "grid", "preview", "speed_mask", "costmap", "nav2_costmap")
CLIPSEG_INPUT_SIDE = 352  # the model's input until a credit announces the service's
_KEY_CHUNK = re.compile(r"^[^*$#?\s/]+$")
MAX_SAFE_MASK_CELLS = 2000  # a side: 4 MB, the most a mask that is the same everywhere should cost


class RelaySettingsError(ValueError):
    pass


def _literal_key(value: str, what: str) -> str:
    if not value or not all(_KEY_CHUNK.match(chunk) for chunk in value.split("/")):
        raise ValueError(f"{what} '{value}' must be a literal zenoh key (chunks without * $ # ? or spaces)")
    return value


class SafeMaskSettings(StrictModel):
    """The robot's own guard of the speed mask (client/relay/mask_guard.py; docs/ros2.md, "When the link dies"):
    when the service goes quiet, the relay hands out the safe mask (the floor everywhere) around the robot."""

    enabled: bool = Field(default=True, description="Guard the speed mask on the robot; false: never a safe mask.")
    after_s: float = Field(
        default=2.0,
        gt=0,
        le=60,
        description="safe_after_s: nothing from the service about the source for this long (or a mask arriving "
        "older than this) and the safe mask replaces the live one. Two periods of the service's default mask rate "
        "(speed.rate_hz 1); keep it above 1 / rate_hz plus the service's latency.",
    )
    floor: float = Field(
        default=0.3, ge=0.01, le=1, description="The safe mask's fraction of maximum speed: the grid's speed.floor."
    )
    max_speed_m_s: float = Field(default=1.5, gt=0, le=50, description="The robot's maximum speed.")
    horizon_s: float = Field(
        default=30.0,
        gt=0,
        le=600,
        description="How long an operator may take to act: the safe mask reaches 2 x max_speed_m_s x horizon_s "
        "each way from the robot (90 m by default), re-centred once it has driven half that.",
    )
    resolution_m: float = Field(
        default=1.0, gt=0, le=100, description="The safe mask's cell size (it is the same everywhere: coarse)."
    )

    @model_validator(mode="after")
    def _mask_bounded(self) -> SafeMaskSettings:
        cells = 4 * self.max_speed_m_s * self.horizon_s / self.resolution_m
        if cells > MAX_SAFE_MASK_CELLS:
            raise ValueError(
                f"safe_mask: {cells:.0f} cells a side (4 x max_speed_m_s x horizon_s / resolution_m) is over "
                f"{MAX_SAFE_MASK_CELLS}: raise resolution_m"
            )
        return self


class RelayCamera(StrictModel):
    """One camera of the robot and the source it becomes."""

    camera: str = Field(
        description="A zenoh key (expression) of images, e.g. 'robot/front/jpeg', or a ROS topic, starting "
        "with '/', e.g. '/camera/front/image_raw'."
    )
    source: str = Field(description="The source name at the service, e.g. 'r1/front' (a literal key).")
    ros_layout: Literal["rmw_zenoh", "bridge"] = Field(
        default="rmw_zenoh", description="How the robot's ROS topics reach zenoh (ROS topics only)."
    )
    ros_domain: int = Field(default=0, ge=0, le=232, description="ROS_DOMAIN_ID (rmw_zenoh keys start with it).")
    ros_message_type: Literal["auto", "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"] = Field(
        default="auto", description="auto: from the rmw_zenoh key; bridge keys carry no type, so set it."
    )
    zenoh_namespace: str = Field(default="", description="The robot's zenoh 'namespace', prefixed to its keys.")
    ros_reliable: bool = Field(
        default=False,
        description="ROS 2 node only: subscribe reliably instead of with the sensor-data QoS (best effort). For "
        "a reliable camera of very large frames: best effort loses a whole frame with any one of its fragments.",
    )
    camera_info: str | None = Field(
        default="auto",
        description="ROS 2 node only (`gcdtrav relay --ros`): the camera's sensor_msgs/CameraInfo topic; auto: "
        "'camera_info' beside the image topic (image_transport's convention: /camera/front/image_raw -> "
        "/camera/front/camera_info); null: none.",
    )
    camera_info_key: str | None = Field(
        default=None,
        description="ROS 2 node only: the link key the CameraInfo goes to as CDR, on change and every "
        "camera_info_period_s (the service's grid camera_info_key); null: checked, not sent.",
    )
    frames: bool = Field(
        default=True,
        description="Send the camera's frames; false: only bring the outputs and guard the speed mask (a robot "
        "whose frames reach the service another way, e.g. rmw_zenoh straight to it).",
    )
    safe_mask: SafeMaskSettings | None = Field(
        default=None,
        description="This camera's guard of the speed mask: the fields it sets replace those of the relay's "
        "safe_mask (and of its flags and parameters); the others are the relay's [the relay's safe_mask].",
    )

    @field_validator("source")
    @classmethod
    def _source_is_literal(cls, value: str) -> str:
        return _literal_key(value, "source")

    @property
    def is_ros(self) -> bool:
        return self.camera.startswith("/")

    @model_validator(mode="after")
    def _ros_type_known(self) -> RelayCamera:
        if self.is_ros and self.ros_layout == "bridge" and self.ros_message_type == "auto":
            raise ValueError(f"camera '{self.camera}': bridge keys carry no type; set ros_message_type")
        if self.zenoh_namespace:
            _literal_key(self.zenoh_namespace, "zenoh_namespace")
        return self


class RelayOdometry(StrictModel):
    """ROS 2 node only: the robot's odometry, sent to a grid's pose stream as Pose2D (about 60 bytes, not the
    700 of a nav_msgs/Odometry with its covariances)."""

    topic: str = Field(default="/odom", description="nav_msgs/Odometry topic on the robot.")
    key: str | None = Field(
        default=None,
        description="The link key of the service grid's pose_key (pose_format: gcdtrav); null: not sent, only "
        "read for the safe mask's centre.",
    )
    max_rate_hz: float = Field(
        default=10.0, gt=0, description="At most this many poses a second cross the link (the grid interpolates)."
    )

    @field_validator("key")
    @classmethod
    def _key_is_literal(cls, value: str | None) -> str | None:
        return None if value is None else _literal_key(value, "odometry key")


class RelayOutcomes(TrackingSettings):
    """Outcomes measured on the robot by the service's own rules (schemas/outcomes.py) and sent over the link
    in batches (docs/calibration.md, "Which robots teach"): velocity tracking from the robot's commands and
    odometry at their full rate, contacts from a bumper, the robot's own TraversalOutcomes, its planned path."""

    source: str | None = Field(
        default=None,
        description="The grid the outcomes belong to, as the service names it [the first camera's source].",
    )
    cmd_vel: str | None = Field(
        default="/cmd_vel",
        description="Velocity commands: a ROS topic (the ROS 2 node: geometry_msgs/Twist or TwistStamped, see "
        "cmd_vel_stamped), or a key of the robot's zenoh bus (Twist2D msgpack or JSON, or an rmw_zenoh Twist key: "
        "CDR); null: no velocity outcomes.",
    )
    cmd_vel_stamped: bool = Field(default=False, description="The commands are TwistStamped (Jazzy's Nav2 option).")
    odometry: str | None = Field(
        default=None,
        description="zenoh relay: the robot's odometry key (Odometry2D msgpack or JSON, or an rmw_zenoh Odometry "
        "key: CDR); the ROS 2 node reads odometry.topic.",
    )
    contact: str | None = Field(
        default=None,
        description="A bumper: std_msgs/Bool (a ROS topic, or an rmw_zenoh key: CDR; JSON true/false on a plain "
        "key). Each press is one contact outcome, score 0, at the robot's pose.",
    )
    outcome: str | None = Field(
        default=None,
        description="zenoh relay: a key of the robot's bus where its own code puts TraversalOutcomes (msgpack or "
        "JSON), sent on with the others.",
    )
    planned_path: str | None = Field(
        default=None,
        description="The robot's planned path: nav_msgs/Path (a ROS topic) or PlannedPath on a zenoh key; sent "
        "when it changes, at most every batch_period_s, shortened to path_length_m ahead.",
    )
    path_length_m: float = Field(default=20.0, gt=0, le=1000, description="How much of the path ahead is sent.")
    path_renew_s: float = Field(
        default=2.0,
        gt=0,
        le=60,
        description="An unchanged path is sent again this often: the service forgets one not renewed within its "
        "ask.path_timeout_s (5 s).",
    )
    batch_period_s: float = Field(
        default=1.0, gt=0, le=60, description="At most one batch of outcomes (and one path) this often."
    )

    @field_validator("source")
    @classmethod
    def _source_is_literal(cls, value: str | None) -> str | None:
        return None if value is None else _literal_key(value, "outcomes.source")

    @field_validator("outcome")
    @classmethod
    def _outcome_is_a_key(cls, value: str | None) -> str | None:
        if value is not None and value.startswith("/"):
            raise ValueError(f"outcomes.outcome '{value}' must be a zenoh key: a TraversalOutcome has no ROS type")
        return value


class RelaySettings(StrictModel):
    cameras: list[RelayCamera] = Field(min_length=1, description="The robot's cameras, one source each.")
    prefix: str = Field(default="gcdtrav", description="The service's key prefix.")
    input_prefix: str = Field(default="gcdtrav/in", description="Where the service takes images (input_key).")
    jpeg_quality: int = Field(default=80, ge=1, le=100, description="JPEG quality of the frames sent.")
    max_side: int | Literal["auto"] = Field(
        default="auto",
        description="auto: the shorter side at the model's input size (the credit announces it), aspect kept; "
        "N: the longer side at most N pixels. Never enlarges.",
    )
    credit_timeout_s: float = Field(
        default=1.5,  # after an outage the lost credit costs this long: 5 s made recovery take 5.7-6.2 s
        gt=0,
        description="Send the newest frame without a credit after this long (a lost credit, a restarted "
        "service); stretched to 3 x the recent time between credits, at most 30 s.",
    )
    stale_after_s: float = Field(
        default=3.0, gt=0, description="Maps of a camera older than this are reported stale (log, health key)."
    )
    camera_silent_after_s: float = Field(
        default=2.0, gt=0, description="A camera with no frame for this long is named as a cause (camera_silent)."
    )
    forward: list[Output] = Field(
        default_factory=lambda: list(FORWARDABLE),
        description="Outputs brought to the robot's bus, each only while a robot-side consumer subscribes.",
    )
    health_period_s: float = Field(default=1.0, gt=0, description="Seconds between RelayHealth messages.")
    link_health_period_s: float | None = Field(
        default=5.0,
        gt=0,
        description="Seconds between RelayHealth messages sent over the link to the service too (its silent-robot "
        "alert hears the robot, and whether a camera is parked; about 0.1 kB/s a camera), and at once when a "
        "camera is parked or runs again; null: never.",
    )
    local_mode: Literal["client", "peer"] = Field(default="client", description="The robot-side session's mode.")
    local_connect: list[str] = Field(
        default_factory=lambda: ["tcp/127.0.0.1:7447"],
        description="The robot's own zenoh router (rmw_zenoh's default), where cameras and consumers are.",
    )
    local_listen: list[str] = Field(default_factory=list, description="Robot-side endpoints to listen on.")
    max_camera_bytes: int = Field(
        default=32_000_000,  # a 4K rgb8 frame is 25 MB
        ge=1000,
        description="A camera message larger than this is not decoded (camera_unusable: too_large).",
    )
    odometry: RelayOdometry | None = Field(default=None, description="ROS 2 node only: odometry to a pose key.")
    safe_mask: SafeMaskSettings = Field(
        default_factory=SafeMaskSettings,
        description="The robot's own guard of the speed mask, every camera's (a camera's own section sets fields "
        "on top of it).",
    )
    outcomes: RelayOutcomes | None = Field(
        default=None, description="Outcomes measured on the robot and sent to the service's experience; null: none."
    )
    pose_key: str | None = Field(
        default=None,
        description="zenoh relay only: the robot's pose on its bus, where the safe mask is centred (Pose2D msgpack, "
        "or a nav_msgs/Odometry CDR: an rmw_zenoh odometry key); the ROS 2 node takes odometry.topic.",
    )
    camera_info_period_s: float = Field(
        default=5.0, gt=0, description="ROS 2 node only: an unchanged CameraInfo is sent again after this long."
    )
    ros_maps: Literal["maps8", "maps"] = Field(
        default="maps8",
        description="ROS 2 node only: T and U (32FC1 images) come from these maps: maps8, 8-bit at "
        "compact_maps_max_side (a tenth of the bytes), or maps, 16-bit at the model's map size.",
    )

    @field_validator("prefix", "input_prefix")
    @classmethod
    def _prefix_is_literal(cls, value: str) -> str:
        return _literal_key(value, "prefix")

    @field_validator("max_side")
    @classmethod
    def _side_positive(cls, value: int | str) -> int | str:
        if isinstance(value, int) and value < 16:
            raise ValueError(f"max_side {value} is below 16 pixels")
        return value

    @model_validator(mode="after")
    def _sources_unique(self) -> RelaySettings:
        sources = [camera.source for camera in self.cameras]
        duplicates = sorted({s for s in sources if sources.count(s) > 1})
        if duplicates:
            raise ValueError(f"sources named twice: {', '.join(duplicates)}")
        return self

    @model_validator(mode="after")
    def _camera_guards_hold(self) -> RelaySettings:
        for camera in self.cameras:  # each camera's own fields on top of the relay's: valid together
            try:
                self.safe_mask_of(camera)
            except ValidationError as err:
                raise ValueError(f"camera {camera.source}: {problems(err, most=3)}") from None
        return self

    def outcome_source(self) -> str:
        """The grid the outcomes belong to."""
        return (self.outcomes.source if self.outcomes else None) or self.cameras[0].source

    def safe_mask_of(self, camera: RelayCamera) -> SafeMaskSettings:
        """The camera's guard: the fields its own section sets, on top of the relay's section (a camera that sets
        only after_s keeps the relay's floor and maximum speed, not the defaults)."""
        if camera.safe_mask is None:
            return self.safe_mask
        own = camera.safe_mask.model_dump(exclude_unset=True)
        return SafeMaskSettings.model_validate({**self.safe_mask.model_dump(), **own})


def layered(below: dict[str, object], above: dict[str, object]) -> dict[str, object]:
    """``above``'s values on top of ``below``'s (None: not given); a section (a dict in both) field by field."""
    merged = dict(below)
    for key, value in above.items():
        lower = merged.get(key)
        if isinstance(value, dict) and isinstance(lower, dict):
            merged[key] = {**lower, **value}
        elif value is not None:
            merged[key] = value
    return merged


def load_relay_settings(file: str | Path | None, overrides: dict[str, object] | None = None) -> RelaySettings:
    """A YAML file's settings with ``overrides`` (flags) on top; a RelaySettingsError naming every problem."""
    data: dict[str, object] = load_mapping(file, "relay settings", RelaySettingsError) if file is not None else {}
    data = layered(data, overrides or {})
    try:
        return RelaySettings.model_validate(data)
    except ValidationError as err:
        where = f"{file}: " if file is not None else ""
        raise RelaySettingsError(where + "invalid relay settings: " + problems(err)) from None
