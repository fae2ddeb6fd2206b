"""Service settings: one pydantic tree that rejects unknown fields.

Sources, later ones winning: defaults < YAML file < ``GCDTRAV_*`` environment variables < command-line flags.
"""

from __future__ import annotations

import json
import os
import re
import socket
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal, get_args

from gcdtrav.schemas.compute_share import ReuseSettings, ScheduleSettings
from gcdtrav.schemas.config import EngineSettings
from gcdtrav.schemas.limits import DEFAULT_MAX_ANCHOR_SET_BYTES
from gcdtrav.schemas.paths import default_cache_dir, default_state_dir, expanded
from gcdtrav.schemas.strict import StrictModel
from gcdtrav.schemas.yaml_file import load_mapping
from pydantic import Field, ValidationError, field_validator, model_validator

ENV_PREFIX = "GCDTRAV_"

# How the model's arithmetic runs. fp32: torch, the reference. bf16: ViT and decoder in bfloat16 (native on
# AVX512-BF16/AMX only). bf16-vit: the ViT only. int8: torch's dynamic int8 ViT. ort-fp32: ONNX Runtime in
# fp32. ort-int8-vit: ONNX Runtime, dynamic int8 ViT, fp32 decoder. ort-int8: also the decoder's MLPs in int8.
# auto: the fastest mode that passes the parity gate, by measurement on this machine at start (cached).
Precision = Literal["auto", "fp32", "bf16", "bf16-vit", "int8", "ort-fp32", "ort-int8-vit", "ort-int8"]
PRECISIONS: tuple[str, ...] = get_args(Precision)
_KEY_CHUNK = re.compile(r"^[^*$#?\s/]+$")


class SettingsError(ValueError):
    pass


def default_instance_name() -> str:
    return f"{socket.gethostname()}-{os.getpid()}"


IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")


class RosInput(StrictModel):
    """ROS 2 camera topics reaching Zenoh through rmw_zenoh or zenoh-bridge-ros2dds (CDR payloads)."""

    key: str = Field(
        description="Key expression, e.g. '0/**/sensor_msgs::msg::dds_::Image_/*' (rmw_zenoh) "
        "or 'camera/front/image_raw' (bridge: the topic name)."
    )
    layout: Literal["rmw_zenoh", "bridge"] = "rmw_zenoh"
    message_type: Literal["auto", "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"] = Field(
        default="auto", description="auto: read from the rmw_zenoh key; bridge keys carry no type, so set it."
    )
    zenoh_namespace: str = Field(
        default="",
        description="The robot's zenoh session 'namespace': its keys (and graph tokens) start with it, e.g. "
        "'robot1' for robot1/0/camera/...; key must start with it too. Outputs are published under it.",
    )

    @model_validator(mode="after")
    def _bridge_needs_a_type(self) -> RosInput:
        if self.layout == "bridge" and self.message_type == "auto":
            raise ValueError(
                f"ros input '{self.key}': bridge keys carry no type; set message_type to one of "
                f"{', '.join(IMAGE_TYPES)}"
            )
        namespace = self.zenoh_namespace
        if namespace and not all(_KEY_CHUNK.match(chunk) for chunk in namespace.split("/")):
            raise ValueError(f"ros input '{self.key}': zenoh_namespace '{namespace}' must be a literal key")
        if namespace and not self.key.startswith(namespace + "/"):
            raise ValueError(f"ros input '{self.key}': the key must start with its zenoh_namespace '{namespace}/'")
        return self


_ROS_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


class RosNode(StrictModel):
    """The service's node in the ROS 2 graph of rmw_zenoh robots (``ros2 node list`` shows /<namespace>/<name>)."""

    name: str = Field(default="gcdtrav", description="ROS node name.")
    namespace: str = Field(default="/", description="ROS namespace of the node, e.g. / or /robot1.")

    @field_validator("name")
    @classmethod
    def _node_name(cls, value: str) -> str:
        if not _ROS_NAME.match(value):
            raise ValueError(f"'{value}' is not a ROS node name (letters, digits and _, not starting with a digit)")
        return value

    @field_validator("namespace")
    @classmethod
    def _node_namespace(cls, value: str) -> str:
        chunks = value.strip("/").split("/") if value != "/" else []
        if not value.startswith("/") or not all(_ROS_NAME.match(chunk) for chunk in chunks):
            raise ValueError(f"'{value}' is not a ROS namespace: '/' or '/name[/name...]'")
        return value.rstrip("/") or "/"


def _topic_template(value: str) -> str:
    name = value.replace("{topic}", "t").strip("/")
    if not name or not all(_ROS_NAME.match(chunk) or chunk == "t" for chunk in name.split("/")):
        raise ValueError(f"'{value}' is not a ROS topic name ({{topic}} stands for the camera's topic)")
    return value


class RosOutput(StrictModel):
    """Maps as ROS 2 topics; ``{topic}`` in a topic stands for the camera's topic (without the leading slash)."""

    enabled: bool = False
    preview: Literal["compressed", "image", "none"] = Field(
        default="compressed",
        description="preview as CompressedImage (jpeg) on <preview_topic>/compressed, as image_transport "
        "names it, as Image (rgb8) on <preview_topic>, or not at all",
    )
    traversability_topic: str = "{topic}/gcdtrav/traversability"
    uncertainty_topic: str = "{topic}/gcdtrav/uncertainty"
    preview_topic: str = "{topic}/gcdtrav/preview"
    occupancy_topic: str = Field(
        default="{topic}/gcdtrav/grid/occupancy",
        description="nav_msgs/OccupancyGrid of the camera's grid, cost 100 (1 - T) (grids with occupancy_grid).",
    )
    grid_uncertainty_topic: str = "{topic}/gcdtrav/grid/uncertainty"
    gridmap_topic: str = Field(
        default="{topic}/gcdtrav/grid/gridmap",
        description="grid_map_msgs/GridMap of the camera's grid, every layer (grids with grid_map).",
    )
    costmap_topic: str = Field(
        default="{topic}/gcdtrav/grid/costmap",
        description="nav_msgs/OccupancyGrid graded for Nav2's static layer (grids with costmap; docs/grid.md).",
    )

    _templates = field_validator(
        "traversability_topic",
        "uncertainty_topic",
        "preview_topic",
        "occupancy_topic",
        "grid_uncertainty_topic",
        "gridmap_topic",
        "costmap_topic",
    )(_topic_template)

    def topic_templates(self) -> list[str]:
        """Every output topic; the compressed preview is a subtopic of the preview's."""
        return [
            self.traversability_topic,
            self.uncertainty_topic,
            self.preview_topic,
            self.preview_topic + "/compressed",
            self.occupancy_topic,
            self.grid_uncertainty_topic,
            self.gridmap_topic,
            self.costmap_topic,
        ]


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


def _one_grid_per_camera(grids: list[GridSettings]) -> None:
    names = [grid.source for grid in grids]
    if len(set(names)) != len(names):
        raise ValueError(f"two grids are published under the same source: {names}")
    cameras = [camera.source for grid in grids for camera in grid.camera_list()]
    if len(set(cameras)) != len(cameras):
        raise ValueError(f"a camera feeds two grids: {cameras}")


class RiskSettings(StrictModel):
    """The risk measures' defaults, for answers whose query names none (docs/risk.md)."""

    alpha: float = Field(
        default=0.1, gt=0, le=1, description="CVaR and quantile level: the worst alpha of the distribution."
    )
    tau: float = Field(
        default=0.3, ge=0, le=1, description="p_below = P(T < tau): the traversability too low to drive."
    )


class ServiceSettings(StrictModel):
    prefix: str = Field(default="gcdtrav", description="Key prefix of every key the service declares.")
    inputs: list[str] = Field(
        default_factory=lambda: ["gcdtrav/in/**"],
        description="Key expressions of image inputs; the source name is the key after the expression's "
        "literal head (the chunks before the first wildcard).",
    )
    model: str | None = Field(default=None, description="CLIPSeg directory or hub id [env GCDTRAV_MODEL].")
    anchors_file: Path | None = Field(default=None, description="Anchor set to start with (JSON/YAML).")
    state_dir: Path = Field(
        default_factory=default_state_dir,
        description="Where the last accepted anchor set is kept across restarts "
        "[$XDG_STATE_HOME/gcdtrav, else ~/.local/state/gcdtrav].",
    )
    cache_dir: Path = Field(
        default_factory=default_cache_dir,
        description="ONNX exports and the measurement of precision auto, shared with gcdtrav doctor and infer "
        "[$XDG_CACHE_HOME/gcdtrav, else ~/.cache/gcdtrav].",
    )
    engine: EngineSettings = Field(default_factory=EngineSettings)
    risk: RiskSettings = Field(default_factory=RiskSettings)
    reuse: ReuseSettings = Field(default_factory=ReuseSettings)
    schedule: ScheduleSettings = Field(default_factory=ScheduleSettings)
    history: int = Field(default=8, ge=1, le=256, description="Frames per source kept for patch queries.")
    history_budget_mb: float = Field(
        default=512,
        gt=0,
        description="Bytes of query history for all sources together, in MB; the oldest frames go first.",
    )
    pending_budget_mb: float = Field(
        default=256,
        gt=0,
        description="Bytes of frames waiting for inference (one per source), in MB; further frames are rejected.",
    )
    max_sources: int = Field(
        default=256, ge=1, description="Sources tracked at once; frames from further new sources are rejected."
    )
    source_idle_s: float = Field(
        default=300, gt=0, description="A source without a frame for this long is forgotten (history, counters)."
    )
    max_candidates: int = Field(
        default=32,
        ge=1,
        description="New sources whose first frame waits to be decoded before they take a slot; a new one evicts "
        "the oldest (a flood of invented names holds at most this many pending frames).",
    )
    reclaim_after_s: float = Field(
        default=2.0,
        ge=0,
        description="When max_sources are tracked, a source with a single frame idle for this long gives its slot "
        "to a new source whose frame decoded (the idlest first); sources with two frames or more keep theirs.",
    )
    max_sources_per_publisher: int | None = Field(
        default=16,
        ge=1,
        description="Sources tracked or waiting per publisher (the zenoh session its samples' source info names); "
        "samples without source info are not capped; null: no cap.",
    )
    max_payload_bytes: int = Field(default=20_000_000, ge=1024, description="Larger payloads are rejected unread.")
    max_stamp_skew_s: float | None = Field(
        default=300.0,
        gt=0,
        description="Frames stamped further than this ahead of their receipt are rejected (skewed_stamp): they "
        "would order their source's maps ahead of later frames; null: no limit. NaN, inf and negative stamps "
        "are always rejected (bad_stamp); stamps in the past are max_frame_age_s's to judge.",
    )
    stall_after_s: float = Field(
        default=2.5,  # issue 26's goal: a hung instance's robots blind at most 3 s beyond their frame time
        gt=0,
        description="An instance whose worker makes no progress for this long with frames queued withdraws "
        "from the fleet (its sources fail over) and reports itself unhealthy until it progresses again; set it a "
        "few seconds above the slowest frame's inference time.",
    )
    max_anchor_set_bytes: int = Field(
        default=DEFAULT_MAX_ANCHOR_SET_BYTES,
        ge=1024,
        description="Larger anchor-set bodies sent to {prefix}/config/anchors are rejected before parsing.",
    )
    max_pixels: int = Field(default=40_000_000, ge=1, description="Larger images are rejected before decoding.")
    max_frame_age_s: float | None = Field(
        default=5.0,
        gt=0,
        description="Frames captured longer ago are dropped (counted stale) at intake and before inference, e.g. "
        "what a link buffered during an outage. Assumes robot and service clocks in step (NTP, chrony); null: "
        "never (robots on simulated time).",
    )
    compact_maps_max_side: int | None = Field(
        default=176,  # half the model's 352: a quarter of the bytes, measured the difference at 2 and 5 Mbit/s
        ge=2,
        description="Longer side of the compact maps ({prefix}/out/{source}/maps8); null: the model's map size.",
    )
    full_resolution: bool = Field(default=False, description="Also publish T and U at the input image's size.")
    preview: bool = Field(default=True, description="Publish a colourised JPEG on {prefix}/out/{source}/preview.")
    preview_max_width: int = Field(default=640, ge=64)
    instance: str = Field(default_factory=default_instance_name, description="Name in results and liveliness.")
    grids: list[GridSettings] = Field(
        default_factory=list, description="Ground grids: one per source, or fusing several cameras."
    )
    ros_inputs: list[RosInput] = Field(default_factory=list, description="ROS 2 image topics (CDR).")
    ros_output: RosOutput = Field(default_factory=RosOutput)
    ros_node: RosNode = Field(default_factory=RosNode)
    precision: Precision = Field(
        default="auto",
        description="Model arithmetic: auto = the fastest mode passing the parity gate, measured on this "
        "machine once and cached (gcdtrav doctor measures it too).",
    )
    measure_before_serving: bool = Field(
        default=False,
        description="precision auto with nothing cached: measure the modes before serving. Default: serve in "
        "fp32 at once, measure in the background, then switch between frames (status says measuring).",
    )
    threads: int | None = Field(
        default=None,
        ge=1,
        description="torch intra-op threads [default: the usable CPUs, within a container's CPU quota].",
    )

    @field_validator("state_dir", "cache_dir")
    @classmethod
    def _expand_home(cls, value: Path) -> Path:
        return expanded(value)

    @field_validator("prefix", "instance")
    @classmethod
    def _literal_key(cls, value: str) -> str:
        chunks = value.split("/")
        if not value or not all(_KEY_CHUNK.match(chunk) for chunk in chunks):
            raise ValueError(f"'{value}' must be a literal zenoh key (chunks without * $ # ? or spaces)")
        return value

    @model_validator(mode="after")
    def _some_input(self) -> ServiceSettings:
        if not self.inputs and not self.ros_inputs:
            raise ValueError("at least one input is needed: inputs (e.g. gcdtrav/in/**) or ros_inputs")
        _one_grid_per_camera(self.grids)
        return self

    @property
    def state_file(self) -> Path:
        """The last accepted anchor set. Named by prefix, not instance: a restarted process must find it."""
        return self.state_dir / f"{self.prefix.replace('/', '_')}.anchors.json"


def _env_overrides(environ: Mapping[str, str]) -> dict[str, Any]:
    """GCDTRAV_HISTORY=4, GCDTRAV_INPUTS='["a/**","b/*"]' or 'a/**,b/*', GCDTRAV_ENGINE__METHOD=argmax."""
    result: dict[str, Any] = {}
    for name, raw in environ.items():
        if not name.startswith(ENV_PREFIX):
            continue
        path = name[len(ENV_PREFIX) :].lower().split("__")
        value: Any = raw
        if path == ["inputs"] and not raw.lstrip().startswith("["):
            value = [part.strip() for part in raw.split(",") if part.strip()]
        elif raw.lstrip().startswith(("[", "{")):
            value = json.loads(raw)
        target = result
        for part in path[:-1]:
            target = target.setdefault(part, {})
        target[path[-1]] = value
    return result


def _merge(base: dict[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    merged = dict(base)
    for key, value in override.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), dict):
            merged[key] = _merge(merged[key], value)
        else:
            merged[key] = value
    return merged


def load_settings(
    file: str | Path | None = None,
    overrides: Mapping[str, Any] | None = None,
    environ: Mapping[str, str] | None = None,
) -> ServiceSettings:
    data = load_mapping(file, "settings file", SettingsError) if file is not None else {}
    env = os.environ if environ is None else environ
    try:
        data = _merge(data, _env_overrides(env))
    except json.JSONDecodeError as err:
        raise SettingsError(f"a {ENV_PREFIX}* variable is not valid JSON: {err}") from None
    data = _merge(data, {k: v for k, v in (overrides or {}).items() if v is not None})
    try:
        return ServiceSettings.model_validate(data)
    except ValidationError as err:
        problems = [f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in err.errors()]
        where = f"{file}: " if file else ""
        raise SettingsError(where + "invalid settings: " + "; ".join(problems)) from None
