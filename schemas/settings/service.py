"""Service settings: one pydantic tree that rejects unknown fields; each section in its own module.

Sources, later ones winning: defaults < YAML file < ``GCDTRAV_*`` environment variables < command-line flags
(the loader: ``settings/env.py``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from gcdtrav.schemas.config import EngineSettings
from gcdtrav.schemas.limits import DEFAULT_MAX_ANCHOR_SET_BYTES
from gcdtrav.schemas.paths import default_cache_dir, default_state_dir, expanded
from gcdtrav.schemas.settings.base import KEY_CHUNK, Precision, default_instance_name
from gcdtrav.schemas.settings.experience import AskSettings, ExperienceSettings
from gcdtrav.schemas.settings.grids import GridSettings, one_grid_per_camera
from gcdtrav.schemas.settings.risk import RiskSettings
from gcdtrav.schemas.settings.ros import RosInput, RosNode, RosOutput
from gcdtrav.schemas.settings.share import ReuseSettings, ScheduleSettings
from gcdtrav.schemas.settings.store import StoreSettings
from gcdtrav.schemas.strict import StrictModel
from pydantic import Field, field_validator, model_validator


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
    experience: ExperienceSettings = Field(default_factory=ExperienceSettings)
    ask: AskSettings = Field(default_factory=AskSettings)
    store: StoreSettings = Field(default_factory=StoreSettings)
    history: int = Field(default=8, ge=1, le=256, description="Frames per source kept for patch queries.")
    history_budget_mb: float = Field(
        default=512,
        gt=0,
        description="Bytes of query history for all sources together, in MB; the oldest frames go first.",
    )
    pending_budget_mb: float = Field(
        default=256,
        gt=0,
        description="Bytes of frames waiting for a glance or inference (at most two per source), in MB; further "
        "frames are rejected.",
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
        description="Frames stamped further than this ahead are rejected (skewed_stamp): with clock: estimated, "
        "ahead of their source's learnt clock (a step forward that holds is learnt again), with clock: synced, "
        "ahead of their receipt; null: no limit. NaN, inf and negative stamps are always rejected (bad_stamp).",
    )
    clock: Literal["estimated", "synced"] = Field(
        default="estimated",
        description="How a frame's age is judged. estimated: by its delay beyond its source's smallest recent "
        "delay, the clock offset learnt per source (robots with wrong clocks are served; status "
        "clock_offset_s). synced: the service's clock minus the capture stamp, for fleets that guarantee NTP.",
    )
    intake_rate_per_publisher: float | None = Field(
        default=240.0,
        gt=0,
        description="Frames a second one publisher (the zenoh session its samples' source info names) may "
        "hand to the intake, in bursts of intake_burst_s; beyond it frames are rejected rate_limited unread. "
        "null: no limit.",
    )
    intake_rate_anonymous: float | None = Field(
        default=1000.0,
        gt=0,
        description="Frames a second shared by every sample without source info (ROS bridges, plain zenoh "
        "puts): a fleet behind one bridge shares it, so size it above the fleet's total frame rate. null: no "
        "limit.",
    )
    intake_burst_s: float = Field(
        default=1.0, gt=0, description="A publisher's bucket holds this many seconds of its rate."
    )
    stall_after_s: float = Field(
        default=2.5,  # issue 26's goal: a hung instance's robots blind at most 3 s beyond their frame time
        gt=0,
        description="An instance whose worker makes no progress for this long with frames queued withdraws "
        "from the fleet (its sources fail over) and reports itself unhealthy until it progresses again; set it a "
        "few seconds above the slowest frame's inference time.",
    )
    shutdown_grace_s: float = Field(
        default=10.0,
        gt=0,
        description="On SIGINT/SIGTERM the instance leaves the fleet at once (its liveliness token goes, the "
        "others take its sources), finishes the frame in flight and exits within this many seconds; a frame "
        "not finished by then is dropped. Kubernetes: keep terminationGracePeriodSeconds a few seconds above.",
    )
    health_port: int = Field(
        default=0,
        ge=0,
        le=65535,
        description="Port of the HTTP probes /livez (the worker progresses) and /readyz (in the fleet, serving); "
        "0: off. For Kubernetes' liveness and readiness probes; answered from memory, no zenoh.",
    )
    health_address: str = Field(
        default="0.0.0.0",
        description="Address the probes listen on once health_port is set: every interface, as a pod's kubelet "
        "probes the pod's IP; 127.0.0.1 keeps them on the box (a local supervisor). They tell only ok or why not.",
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
        description="Frames older than this are dropped (counted stale) at intake, before inference and before "
        "publishing, e.g. what a link buffered during an outage; the age as clock says. null: never (replayed "
        "bags, simulated time).",
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
    allow_mixed_models: bool = Field(
        default=False,
        description="Take sources even when this instance's model (checkpoint fingerprint) differs from the fleet's "
        "(the model of the instance serving longest). Off: such an instance takes no sources and says why. On for "
        "the new instances of a rolling model upgrade (deploy/README.md).",
    )
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
    metrics_port: int = Field(
        default=0,
        ge=0,
        le=65535,
        description="TCP port of the Prometheus metrics (HTTP GET /metrics, docs/metrics.md) [env "
        "GCDTRAV_METRICS_PORT]; 0: off, nothing listens. Off by default: the endpoint has no authentication (the "
        "zenoh side has ACL and TLS) and names the fleet's sources, so it opens only where asked for.",
    )
    metrics_address: str = Field(
        default="0.0.0.0",
        min_length=1,
        description="Address the metrics port listens on. All interfaces by default: a port set is meant for a "
        "Prometheus elsewhere (a pod's IP in Kubernetes); 127.0.0.1 keeps it on the box.",
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
        if not value or not all(KEY_CHUNK.match(chunk) for chunk in chunks):
            raise ValueError(f"'{value}' must be a literal zenoh key (chunks without * $ # ? or spaces)")
        return value

    @model_validator(mode="after")
    def _some_input(self) -> ServiceSettings:
        if not self.inputs and not self.ros_inputs:
            raise ValueError("at least one input is needed: inputs (e.g. gcdtrav/in/**) or ros_inputs")
        one_grid_per_camera(self.grids)
        if self.experience.enabled and not self.grids:
            raise ValueError("experience: enabled needs a ground grid (grids:): outcomes pair with its cells")
        if self.ask.enabled and not self.experience.enabled:
            raise ValueError("ask: enabled needs experience: enabled (an answer becomes outcomes of the experience)")
        return self

    @property
    def state_file(self) -> Path:
        """The last accepted anchor set. Named by prefix, not instance: a restarted process must find it."""
        return self.state_dir / f"{self.prefix.replace('/', '_')}.anchors.json"
