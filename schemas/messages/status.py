"""The status block: what an instance says of itself, its sources, grids and experience (`gcdtrav status`),
and what the viewer shows of one source."""

from __future__ import annotations

from gcdtrav.schemas.config import Method
from gcdtrav.schemas.messages.base import Message
from gcdtrav.schemas.messages.maps import MapsHeader
from gcdtrav.schemas.strict import WireModel
from pydantic import Field


class CameraPlacement(WireModel):
    """Where a camera's body frame (x forward, y left, z up) sits in the robot's base frame: metres and radians,
    R = Rz(yaw) Ry(pitch) Rx(roll), as the settings' mount: (docs/grid.md)."""

    x: float
    y: float
    z: float
    roll: float
    pitch: float
    yaw: float


class GridCameraStatus(WireModel):
    """What a grid knows of one of its cameras."""

    intrinsics: str | None = Field(
        default=None, description="Where its intrinsics come from: 'settings' or 'camera_info'; None: not yet."
    )
    mount: str | None = Field(
        default="settings",
        description="Where its mount comes from: 'settings' or 'tf'; None: not yet (tf.mount, no transform yet).",
    )
    not_fused: str = Field(default="", description="Why its last frame was not fused; '': it was (or none came).")
    placement: CameraPlacement | None = Field(
        default=None,
        description="The mount the grid projects its frames with, from wherever mount says (a viewer draws the "
        "camera there). None: not known yet, or an older writer. Since 1.4.",
    )


class GridStatus(WireModel):
    """How one ground grid is doing (docs/grid.md, *The grid in the status*)."""

    source: str = Field(description="The name it is published under.")
    frame_id: str = Field(description="Its frame: the pose stream's, or 'base_link' without one.")
    fused: int = Field(default=0, description="Frames fused so far.")
    not_fused_by_reason: dict[str, int] = Field(
        default_factory=dict,
        description="Frames of its cameras not fused: no_intrinsics, no_mount, no_pose, before_poses, pose_too_old, "
        "pose_gap (docs/grid.md).",
    )
    newest_fused_stamp: float | None = Field(default=None, description="Capture stamp of the newest fused frame.")
    fused_ago_s: float | None = Field(default=None, description="Service seconds since the last fusion.")
    pose_age_s: float | None = Field(
        default=None, description="Service seconds since its pose stream's last pose; None: none received."
    )
    pose_clock_s: float | None = Field(
        default=None,
        description="Its first camera's learnt clock offset minus the pose stream's (both learnt by "
        "schemas/delay_window.py): the pose clock minus the camera's plus the links' smallest delays' difference; "
        "near 0 when both run on the robot's clock, far from 0 frames find no pose at their stamp. None: not known.",
    )
    poses_held: int = Field(default=0, description="Poses in its buffer.")
    cameras: dict[str, GridCameraStatus] = Field(default_factory=dict)
    costmap_ago_s: float | None = Field(
        default=None, description="Service seconds since the last costmap went out; None: none (or costmap off)."
    )
    speed_ago_s: float | None = Field(
        default=None,
        description="Service seconds since the last speed filter mask went out; None: none (or speed off). Since 1.5.",
    )
    speed_safe: bool | None = Field(
        default=None,
        description="Whether that mask is the safe one (the floor everywhere: the grid went stale, or the service "
        "stops); None: none. Since 1.5.",
    )
    problem: str = Field(default="", description="Why it fuses nothing, when frames come and none fused for a while.")
    tf_waiting: dict[str, str] = Field(
        default_factory=dict,
        description="A grid with tf: what tf does not give yet ('pose', or a camera for its mount) and why (the "
        "lookup's error: tf_unknown_frame, tf_no_chain, ...).",
    )


class SourceStatus(WireModel):
    received: int = 0
    processed: int = 0
    dropped: int = Field(
        default=0,
        description="Good frames never published: replaced by a newer one before inference, stale, or at shutdown.",
    )
    rejected: int = Field(default=0, description="Undecodable, oversized or malformed payloads.")
    last_seq: int | None = None
    latency_ms: dict[str, float] = Field(default_factory=dict, description="Receive-to-publish p50/p90/p99.")
    inference_ms: dict[str, float] = Field(default_factory=dict)
    stale: int = Field(default=0, description="Of the dropped: captured over max_frame_age_s ago.")
    bytes_per_s: float | None = Field(default=None, description="Input payload bytes per second, last 10 s.")
    frame_age_ms: dict[str, float] = Field(
        default_factory=dict,
        description="Age at intake p50/p95, as the service's clock setting judges it: the delay beyond the "
        "source's smallest recent delay (estimated), or receipt minus capture stamp (synced).",
    )
    credits: int = Field(default=0, description="Credits granted to the source (CreditGrant).")
    dropped_by_reason: dict[str, int] = Field(
        default_factory=dict, description="Its dropped frames by reason (replaced, stale, ...). Since 1.2."
    )
    rejected_by_reason: dict[str, int] = Field(
        default_factory=dict, description="Its rejected frames by reason (undecodable, oversized, ...). Since 1.2."
    )
    problem: str = Field(
        default="",
        description="Why its last frame gave no maps ('reason: detail', e.g. 'stale: captured 3600.0 s ago, ...'); "
        "empty once maps are published. Since 1.2.",
    )
    refused: bool = Field(
        default=False,
        description="A source refused before it took a slot (every frame stale or undecodable so far, or no slot "
        "left), listed with its counts and problem (at most 32 such sources). Since 1.2.",
    )
    clock_offset_s: float | None = Field(
        default=None,
        description="The source's clock as learnt from its stamped frames: the smallest recent receipt minus "
        "capture stamp, i.e. service minus robot clock plus the link's smallest delay; None before a stamped "
        "frame. Since 1.2.",
    )
    unchanged: int = Field(
        default=0,
        description="Frames not inferred because the view had not changed: the last maps were published again "
        "(MapsHeader.computed_from). received = processed + unchanged + dropped + rejected, plus the frames "
        "waiting or in flight. Since 1.3.",
    )
    weight: float | None = Field(
        default=None, description="The scheduler's weight of the source (schedule.policy need; None: round-robin)."
    )
    share: float | None = Field(
        default=None, description="The source's share of this instance's inferences over the last 10 s."
    )


class QuestionStatus(WireModel):
    """An open OperatorQuestion as the status shows it (the question without its crop)."""

    id: str
    source: str
    stamp: float
    reason: str = Field(description="ambiguous or novel.")
    concepts: list[str] = Field(description="The two competing concepts, strongest first.")
    region: tuple[float, float, float, float] = Field(description="(x0, y0, x1, y1) in the grid's frame, m.")
    cells: int | None = Field(
        default=None, description="The region's cells: an answer makes one operator pair per cell; None: older."
    )


class StoreStatus(WireModel):
    """The store of pairs and anchor history as this instance sees it (docs/calibration.md, "Where pairs live")."""

    backend: str = Field(description="sqlite (a file in the state dir) or postgresql (the fleet's database).")
    location: str = Field(description="The file, or the database URL (never with a password).")
    reachable: bool
    unreachable_since: float | None = Field(
        default=None, description="Since when it could not be reached or written, s since the epoch; None: it can."
    )
    error: str | None = Field(default=None, description="The last failure, one line; None while reachable.")
    pending_pairs: int = Field(default=0, description="Pairs waiting in memory to be written (store.outbox_pairs).")
    written_pairs: int = Field(default=0, description="Pairs this instance wrote since it started.")
    dropped_pairs: int = Field(default=0, description="Pairs refused: the outbox was full while the store was down.")


class ExperienceStatus(WireModel):
    """The experience of an instance (docs/calibration.md): its grid, pairs and counters, open questions."""

    source: str = Field(description="The grid the outcomes belong to.")
    pairs: int = Field(description="Stored pairs in the store (the whole fleet's), every concept tuple.")
    stored_bytes: int = 0
    counts: dict[str, int] = Field(
        default_factory=dict, description="outcomes, pairs, rejected_* and ignored_* by reason, velocity_*, ask_*."
    )
    open_questions: list[QuestionStatus] = Field(default_factory=list)


class ServiceStatus(Message):
    instance: str
    instances: list[str] = Field(default_factory=list, description="Live instances of this prefix, as seen here.")
    uptime_s: float
    model: str
    anchor_set_version: str
    method: Method
    precision: str = Field(
        default="",
        description="The mode running now (service/backends/modes.py): fp32, bf16, bf16-vit, int8, ort-fp32, "
        "ort-int8-vit or ort-int8.",
    )
    precision_reason: str = Field(
        default="", description="Why this mode runs: asked for, or auto's measurements on this machine (ms per frame)."
    )
    measuring: bool = Field(
        default=False,
        description="precision auto is timing the modes on this machine in the background; precision is the safe "
        "mode meanwhile, then auto's choice. Since 1.2.",
    )
    queued: int = Field(description="Frames waiting for inference (at most one per source).")
    queued_bytes: int = Field(default=0, description="Their payload bytes (at most pending_budget_mb).")
    sources: dict[str, SourceStatus]
    rejected_by_reason: dict[str, int]
    dropped_by_reason: dict[str, int] = Field(
        default_factory=dict, description="Dropped frames by reason: replaced (latest-only), shutdown. Since 1.1."
    )
    last_errors: list[str]
    history_bytes: int = Field(default=0, description="Bytes of weights kept for patch queries, all sources.")
    history_budget_bytes: int = Field(default=0, description="The history's limit (history_budget_mb).")
    tracked_sources: int = Field(default=0, description="Sources the service keeps state for now.")
    max_sources: int = Field(default=0, description="The limit of tracked sources (max_sources).")
    healthy: bool | None = Field(
        default=None,
        description="False while the worker makes no progress with frames queued (stall_after_s): the "
        "instance has withdrawn its liveliness token and serves no source. None: an instance before 1.2.",
    )
    reason: str = Field(default="", description="Why it is unhealthy, or what it last recovered from. Since 1.2.")
    anchor_set_accepted_at: float | None = Field(
        default=None, description="When the active anchor set was accepted in the fleet, s since epoch. Since 1.2."
    )
    anchor_sets: dict[str, str] = Field(
        default_factory=dict,
        description="The active anchor set version of every live instance, as this one last learnt it; more "
        "than one distinct version is a divergence. Since 1.2.",
    )
    experience: ExperienceStatus | None = Field(
        default=None, description="Experience counts and open questions; None: experience off. Since 1.3."
    )
    store: StoreStatus | None = Field(
        default=None, description="The store of pairs and anchor history; None: an older writer. Since 1.5."
    )
    grids: list[GridStatus] | None = Field(
        default=None, description="Each ground grid's health; None: no grids (or an older writer). Since 1.4."
    )
    model_fingerprint: str = Field(
        default="", description="A hash of the checkpoint's config and weight files; empty: unknown. Since 1.4."
    )
    model_refused: str = Field(
        default="",
        description="Why this instance takes no sources: its model differs from the fleet's (allow_mixed_models "
        "off). Empty: it takes its share. Since 1.4.",
    )
    instance_models: dict[str, str] = Field(
        default_factory=dict,
        description="The model fingerprint of every live instance that advertises one, as this one knows it. "
        "Since 1.4.",
    )


class SourceView(Message):
    """What `gcdtrav view` shows of one source on its status channel (JSON): the latest maps' header and the
    source's counters on every instance that tracks it."""

    source: str
    maps: MapsHeader | None = Field(default=None, description="Header of the latest maps received.")
    latency_ms: float | None = Field(default=None, description="Input stamp to the viewer's receipt of the maps.")
    instances: dict[str, SourceStatus] = Field(default_factory=dict, description="Counters per instance.")
