"""Messages on the bus. Every payload is msgpack of one of these models (see docs/messages.md).

Service and client both import this module, so a field changes in exactly one place.
"""

from __future__ import annotations

import json
import re
from enum import Enum
from typing import Any, TypeVar

import msgpack
import numpy as np
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.config import Method
from gcdtrav.schemas.limits import MAX_FRAME_ID_CHARS, Coordinate, FiniteFloat
from gcdtrav.schemas.strict import WireModel
from numpy.typing import NDArray
from pydantic import Field, ValidationError, field_validator

MSGPACK_ENCODING = "application/msgpack"
# major.minor of every message below. A minor step adds fields (older readers ignore them); a major step
# changes or removes one, and a reader refuses a message of another major with both versions named.
# 1.0 was the integer 1 in MapsHeader only; 1.1 puts the version in every message and adds risk fields;
# 1.2 adds ServiceStatus.measuring, MapsHeader.order, the status's health and anchor-set fleet fields, and the
# grid's planner layers (GridMessage, GridHeader).
SCHEMA_VERSION = "1.5"
_VERSION = re.compile(r"^(\d+)(?:\.\d+)?$")


class MessageError(ValueError):
    """A payload that is not a valid message of the expected type."""


class MessageTooLarge(MessageError):
    """A payload over the size its reader accepts: refused unread."""


def check_size(name: str, payload: bytes, max_bytes: int | None) -> None:
    """Refuse a payload of ``name`` over ``max_bytes`` before reading it (None: no limit)."""
    if max_bytes is not None and len(payload) > max_bytes:
        raise MessageTooLarge(f"{name} of {len(payload)} bytes exceeds the limit of {max_bytes}")


class SchemaVersionError(MessageError):
    """A message of another major schema version: its fields may mean something else here."""


def schema_major(version: object) -> int:
    """The major of '1.2', '1' or 1 (a 1.0 writer's integer); a MessageError for anything else."""
    match = _VERSION.match(str(version)) if isinstance(version, (int, str)) and not isinstance(version, bool) else None
    if match is None:
        raise MessageError(f"schema_version {version!r} is not 'major.minor'")
    return int(match.group(1))


def check_schema_version(name: str, version: object) -> None:
    """Accept this major with any minor (newer minors only add fields); refuse another major."""
    if schema_major(version) != schema_major(SCHEMA_VERSION):
        raise SchemaVersionError(
            f"{name} has schema version {version}, this reader reads {schema_major(SCHEMA_VERSION)}.x "
            f"(it has {SCHEMA_VERSION}): upgrade or downgrade gcdtrav on one side"
        )


class Message(WireModel):
    """A whole payload on the bus. Packed with the writer's ``schema_version``; read under the wire rule:
    unknown fields ignored, another major refused (schemas/strict.py)."""

    schema_version: str = Field(default=SCHEMA_VERSION, description="major.minor of the writer's schemas.")

    def pack(self) -> bytes:
        return msgpack.packb(self.model_dump(mode="python"), use_bin_type=True)

    @classmethod
    def unpack(cls: type[M], payload: bytes, max_bytes: int | None = None) -> M:
        check_size(cls.__name__, payload, max_bytes)
        try:
            data = msgpack.unpackb(payload, raw=False, strict_map_key=True)
        except (ValueError, msgpack.UnpackException, TypeError) as err:
            raise MessageError(f"not a msgpack {cls.__name__}: {err}") from None
        if not isinstance(data, dict):
            raise MessageError(f"a {cls.__name__} must be a msgpack map, got {type(data).__name__}")
        return cls.validated(data)

    @classmethod
    def decode(cls: type[M], payload: bytes, max_bytes: int | None = None) -> M:
        """The message in msgpack, or in JSON (a payload starting with '{'), as a person or a script without
        msgpack sends it; MessageTooLarge over ``max_bytes``, MessageError naming what else is wrong."""
        check_size(cls.__name__, payload, max_bytes)
        if payload.lstrip()[:1] != b"{":
            return cls.unpack(payload)
        try:
            data = json.loads(payload)
        except (ValueError, UnicodeDecodeError) as err:
            raise MessageError(f"not a JSON {cls.__name__}: {err}") from None
        if not isinstance(data, dict):
            raise MessageError(f"a {cls.__name__} must be a JSON object")
        return cls.validated(data)

    @classmethod
    def validated(cls: type[M], data: dict[str, Any]) -> M:
        """The message from decoded fields (msgpack, or a ROS message's), or a MessageError naming the fields."""
        if "schema_version" in data:  # a 1.0 writer sent none: same major
            check_schema_version(cls.__name__, data["schema_version"])
            data = {**data, "schema_version": str(data["schema_version"])}
        try:
            return cls.model_validate(data)
        except ValidationError as err:
            problems = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in err.errors()[:5])
            raise MessageError(f"invalid {cls.__name__}: {problems}") from None


M = TypeVar("M", bound=Message)


def peek_fields(payload: bytes, names: tuple[str, ...]) -> dict[str, Any]:
    """Some top-level fields of a msgpack message, skipping the others unread (a frame's pixels, a map's
    PNGs): a message's stamp at intake costs no copy of its data. Missing fields are absent; a MessageError
    if ``payload`` is not a msgpack map."""
    unpacker = msgpack.Unpacker(raw=False, strict_map_key=True, max_buffer_size=max(len(payload), 1))
    found: dict[str, Any] = {}
    try:
        unpacker.feed(payload)
        for _ in range(unpacker.read_map_header()):
            key = unpacker.unpack()
            if key in names:
                found[key] = unpacker.unpack()
                if len(found) == len(names):
                    break
            else:
                unpacker.skip()
    except (ValueError, msgpack.UnpackException, msgpack.OutOfData, TypeError) as err:
        raise MessageError(f"not a msgpack map: {type(err).__name__}: {err}") from None
    return found


# ---- images in -------------------------------------------------------------------------------------


class PixelEncoding(str, Enum):
    RGB8 = "rgb8"
    BGR8 = "bgr8"
    MONO8 = "mono8"
    JPEG = "jpeg"
    PNG = "png"


RAW_CHANNELS = {PixelEncoding.RGB8: 3, PixelEncoding.BGR8: 3, PixelEncoding.MONO8: 1}


class ImageEnvelope(Message):
    """An image with its capture time and camera frame, as the client library publishes it."""

    stamp: float = Field(description="Capture time, seconds since the Unix epoch.")
    frame_id: str = Field(
        default="",
        max_length=MAX_FRAME_ID_CHARS,
        description="The camera's coordinate frame, passed through to the maps.",
    )
    encoding: PixelEncoding
    width: int = Field(ge=1)
    height: int = Field(ge=1)
    data: bytes = Field(description="Row-major pixels (raw encodings) or the compressed file (jpeg, png).")
    sent_at: float | None = Field(
        default=None,
        description="When the sender published it, its own clock (a relay sets it): echoed in the credit, so the "
        "sender can estimate the link's round trip and the clock offset.",
    )
    original_size: tuple[int, int] | None = Field(
        default=None,
        description="(width, height) of the camera's image when the sender shrank it (a relay does): the maps' "
        "geometry and the answers' pixels are in it. None: the image is the camera's. Since 1.2.",
    )

    @field_validator("original_size")
    @classmethod
    def _positive_size(cls, value: tuple[int, int] | None) -> tuple[int, int] | None:
        if value is not None and min(value) < 1:
            raise ValueError(f"{value} must be (width, height), each at least 1")
        return value


# ---- maps out --------------------------------------------------------------------------------------


class MapsHeader(WireModel):
    source: str = Field(description="The source: the input key after the matched prefix, e.g. 'r1/front'.")
    key: str = Field(description="The full key the image arrived on.")
    seq: int = Field(description="Per-source sequence number of processed frames, from 0.")
    stamp: float = Field(description="Input capture time (envelope stamp, or receive time for bare images), s.")
    frame_id: str = ""
    received_at: float = Field(description="When the service received the image, s since epoch.")
    published_at: float = Field(description="When the service published this message, s since epoch.")
    inference_ms: float = Field(description="Model forward time for this frame, ms.")
    model: str
    instance: str = Field(description="The service instance that made this result.")
    anchor_set_version: str
    method: Method
    map_shape: tuple[int, int] = Field(description="(height, width) of T and U in this message.")
    image_size: tuple[int, int] = Field(
        description="(width, height) of the camera's image, pixels: the input's, or the original_size a relay sent "
        "with a shrunk frame. Pixel coordinates of queries are in it."
    )
    scale: tuple[float, float] = Field(description="(sx, sy): image_size pixels per patch along x and y.")
    order: tuple[float, float] | None = Field(
        default=None,
        description="The source's order across instances and hand-overs: (stamp, received_at), compared as a "
        "tuple; a map whose order is not above the last one shown of its source is older (or the same frame "
        "again) and is dropped by the client. seq counts per instance and does not order. Since 1.2.",
    )
    computed_from: tuple[float, int] | None = Field(
        default=None,
        description="(stamp, seq) of the frame these maps were computed from when it is not this one: this "
        "frame's view had not changed since, so it was not inferred and that frame's maps were published again "
        "(seq is then that frame's; stamp and order are this frame's). None: computed from this frame. Since 1.3.",
    )
    age_at_receipt_s: float | None = Field(
        default=None,
        description="How old the frame was when the service received it, as the service judged it (never "
        "negative): its delay beyond its source's smallest recent one (clock: estimated, whatever the robot's "
        "clock reads), or the service's clock minus the stamp (clock: synced). None: no usable stamp, or a "
        "writer before 1.4. Maps.age_s adds the time since on clocks that need not agree. Since 1.4.",
    )


class MapsMessage(Message):
    """T and U of one frame: 16-bit PNGs, value = round(x * 65535)."""

    header: MapsHeader
    traversability_png: bytes
    uncertainty_png: bytes
    traversability_full_png: bytes | None = Field(default=None, description="At image size, if enabled.")
    uncertainty_full_png: bytes | None = None


class CompactMapsMessage(Message):
    """T and U of one frame for slow links: 8-bit PNGs, value = round(x * 255), at ``header.map_shape`` (the
    model's map, or smaller: ``compact_maps_max_side``), ``header.scale`` for that shape."""

    header: MapsHeader
    traversability_png: bytes
    uncertainty_png: bytes


# ---- credits: a robot's relay sends a frame only when the service is ready for it -------------------


class CreditGrant(Message):
    """The source's owner freed the source's slot: the relay may send its next frame (docs/messages.md)."""

    source: str
    instance: str = Field(description="The instance that owns the source and granted this credit.")
    grant: int = Field(description="Credits this instance granted the source so far, from 0.")
    reason: str = Field(
        description="What freed the slot: 'taken' (the frame went to inference), 'unchanged' (not inferred, its "
        "view had not changed: the last maps went out again), 'refresh' (an unchanged view past max_reuse_s waits "
        "for inference; later unchanged frames are answered meanwhile), 'stale' (older than max_frame_age_s) or "
        "'refused' (rejected at intake).",
    )
    granted_at: float = Field(description="The service's clock, s since epoch.")
    model_input: tuple[int, int] = Field(
        description="(width, height) the model resizes every image to: more pixels are wasted on the link."
    )
    max_frame_age_s: float | None = Field(description="Frames older than this are dropped; None: never.")
    frame_stamp: float | None = Field(default=None, description="Capture stamp of the frame that freed the slot.")
    frame_sent_at: float | None = Field(default=None, description="Its envelope's sent_at (the sender's clock).")
    frame_received_at: float | None = Field(default=None, description="When the service received it, its clock.")
    last_maps_stamp: float | None = Field(
        default=None, description="Capture stamp of the newest frame whose maps this instance published."
    )
    problem: str | None = Field(
        default=None,
        description="Why the source's last frame gave no maps, as the service counted it ('reason: detail', e.g. "
        "'stale: captured 3600.0 s ago, over max_frame_age_s = 5 s ...'); None once maps are published. Since 1.2.",
    )


class RelayHealth(Message):
    """What a robot's relay knows of one camera, on the robot's bus once a second (docs/messages.md)."""

    source: str
    published_at: float = Field(description="The robot's clock, s since epoch.")
    newest_map_stamp: float | None = Field(
        description="Capture stamp of the newest maps (or grid) that reached the relay, or that the owner "
        "reported publishing in a credit; None before any."
    )
    map_age_s: float | None = Field(description="published_at - newest_map_stamp; None before any maps.")
    stale: bool = Field(description="No maps newer than stale_after_s: slow down or stop.")
    stale_after_s: float
    frames_captured: int = Field(description="Camera frames the relay received.")
    frames_sent: int = Field(description="Frames sent to the service (the rest were replaced by newer ones).")
    credit_timeouts: int = Field(description="Frames sent without a credit after the timeout (credit lost).")
    uplink_bytes_per_s: float = Field(description="Payload bytes sent to the service, last 10 s.")
    downlink_bytes_per_s: float = Field(description="Payload bytes forwarded from the service, last 10 s.")
    owner: str | None = Field(default=None, description="The instance of the last credit.")
    clock_offset_s: float | None = Field(
        default=None, description="Service clock minus robot clock, estimated from credit round trips."
    )
    round_trip_s: float | None = Field(default=None, description="Link round trip of the best recent estimate.")
    problem: str | None = Field(
        default=None,
        description="Why the service gives no maps, as its last credit said (CreditGrant.problem), or the "
        "relay's own (camera frames not usable). Since 1.2.",
    )
    causes: dict[str, str] = Field(
        default_factory=dict,
        description="What may keep this camera's maps stale, by cause: camera_silent, no_instance, service_refuses, "
        "camera_unusable, camera_clock (client/relay/causes.py), each with a sentence; empty: none known. Since 1.4.",
    )
    parked: bool = Field(
        default=False,
        description="The robot stopped this camera on purpose (CameraParked on its bus): its silence is no fault, "
        "the silent-robot alert stays quiet. The relay also sends its health over the link every "
        "link_health_period_s, so the service knows. Since 1.5.",
    )


class CameraParked(Message):
    """{prefix}/relay/{source}/parked, on the robot's bus: the robot's own software says it stops (parked: true)
    or restarts (false) a camera on purpose; the relay marks its RelayHealth until told otherwise."""

    parked: bool = Field(description="True: the camera is stopped on purpose; false: it runs again.")
    reason: str = Field(default="", max_length=200, description="Why, for the operator (e.g. 'charging').")


# ---- queries ---------------------------------------------------------------------------------------


class AnchorPoint(WireModel):
    """An anchor as a distribution reports it: the wire's copy of the configuration's ``Anchor``."""

    concept: str
    position: float
    width: float = Field(description="The effective width (the set's default where the anchor gives none).")


class ContextDistribution(Message):
    """The Gaussian Context Distribution of one patch (or the mean of a region's patch weights)."""

    source: str
    seq: int | None = Field(default=None, description="Patch queries: the frame's sequence number. Cells: none.")
    stamp: float
    frame_id: str = ""
    anchor_set_version: str
    anchors: list[AnchorPoint] = Field(description="Concept, position and effective width of every anchor.")
    weights: list[float] = Field(description="Softmax weight of each anchor, same order as anchors.")
    patch: tuple[int, int] | None = Field(default=None, description="Patch queries: (i, j) = (row, column) in the map.")
    region: tuple[int, int, int, int] | None = Field(
        default=None, description="Patches pooled: (i0, j0, i1, j1), end exclusive."
    )
    mean: float = Field(description="mu: the traversability T of this distribution.")
    std: float = Field(description="sigma: the uncertainty U (not normalised).")
    skewness: float
    excess_kurtosis: float
    entropy: float = Field(description="Entropy of the weights, nats.")
    modes: int
    top_anchors: list[int]
    density_x: list[float] = Field(description="Grid on [0, 1] where the density is sampled.")
    density: list[float] = Field(description="Mixture density at density_x (zero widths drawn at the bandwidth).")
    density_bandwidth: float
    alpha: float | None = Field(default=None, description="The level of quantile and cvar. Since 1.1.")
    tau: float | None = Field(default=None, description="The threshold of p_below. Since 1.1.")
    quantile: float | None = Field(default=None, description="Lower alpha-quantile of T. Since 1.1.")
    cvar: float | None = Field(default=None, description="CVaR_alpha: the mean of T over its worst alpha. Since 1.1.")
    p_below: float | None = Field(default=None, description="P(T < tau). Since 1.1.")
    match: float | None = Field(
        default=None, description="The best concept's own score (sigmoid of its logit): low = novel. Since 1.1."
    )
    cell: tuple[int, int] | None = Field(default=None, description="Grid queries: (i, j) = (row, column) in the grid.")
    cell_xy: tuple[float, float] | None = Field(default=None, description="Grid queries: the cell's centre, m.")
    observations: int | None = Field(default=None, description="Grid queries: pixels fused into the cell.")
    grid_updates: int | None = Field(default=None, description="Grid queries: the grid's updates so far (its seq).")

    def weights_array(self) -> NDArray[np.float32]:
        return np.asarray(self.weights, dtype=np.float32)


class Pose2D(Message):
    """The robot's pose in its odometry frame, as a grid's pose stream (or nav_msgs/Odometry CDR)."""

    stamp: FiniteFloat
    frame_id: str = Field(default="odom", max_length=MAX_FRAME_ID_CHARS)
    x: Coordinate = Field(description="Metres in the odometry frame.")
    y: Coordinate
    yaw: FiniteFloat = Field(description="Heading, radians, counter-clockwise from x.")


class GridHeader(WireModel):
    source: str
    seq: int = Field(description="Grid updates so far.")
    stamp: float = Field(description="Stamp of the last fused frame.")
    frame_id: str = Field(description="'base_link' (no pose stream) or the pose stream's frame.")
    origin: tuple[float, float] = Field(description="(x, y) of the corner of cell (0, 0), metres.")
    resolution: float = Field(description="Cell side, metres.")
    cells: int = Field(description="The grid is cells x cells; row i is y, column j is x.")
    robot: tuple[float, float, float] | None = Field(default=None, description="(x, y, yaw) in the grid frame.")
    anchor_set_version: str
    resets: int = Field(description="Times the grid was cleared (anchor set changes).")
    last_reset: str = ""
    known_cells: int
    instance: str
    alpha: float | None = Field(default=None, description="The level of the cvar layer. Since 1.2.")
    tau: float | None = Field(default=None, description="The threshold of the p_below layer. Since 1.2.")
    expired_cells: int | None = Field(
        default=None, description="Cells observed once but not for max_age_s: unknown again. Since 1.2."
    )
    age_s: float | None = Field(
        default=None,
        description="Publication time minus stamp (the last fused frame's), s: the grid's own age, clock skew "
        "included. Since 1.2.",
    )
    capture_stamp: float | None = Field(
        default=None,
        description="Capture stamp of the frame this update fused (stamp is the newest fused; a frame of "
        "another camera may be older). None: an older writer.",
    )
    capture_pose: tuple[float, float, float] | None = Field(
        default=None,
        description="(x, y, yaw) in the grid frame the frame was projected from: the robot's pose at "
        "capture_stamp, interpolated from the pose stream (robot is the newest pose). None: no pose stream "
        "(the grid is in base_link), or an older writer.",
    )


class GridMessage(Message):
    """T and U per cell as 16-bit PNGs (value / 65535) and observation counts (16-bit, capped); a cell with
    count 0 is unknown, whatever its other pixels hold. Since 1.2 the planner's layers too (absent from older
    writers): CVaR at header.alpha, P(T < header.tau) and the fused match score as 16-bit PNGs (value / 65535),
    and each cell's age (16-bit PNG of tenths of a second before header.stamp, 65535: never observed)."""

    header: GridHeader
    traversability_png: bytes
    uncertainty_png: bytes
    count_png: bytes
    cvar_png: bytes | None = Field(default=None, description="CVaR_alpha of T per cell. Since 1.2.")
    p_below_png: bytes | None = Field(default=None, description="P(T < tau) per cell. Since 1.2.")
    match_png: bytes | None = Field(default=None, description="Fused match score per cell. Since 1.2.")
    age_png: bytes | None = Field(
        default=None, description="Seconds since each cell was last observed, in 0.1 s steps. Since 1.2."
    )


class PathReply(Message):
    source: str
    stamp: float
    anchor_set_version: str
    points: list[tuple[float, float]] = Field(description="The polyline asked for, metres.")
    cells: list[ContextDistribution] = Field(description="Known cells along it, in order.")
    unknown_cells: int = Field(description="Cells along the path never observed (not in ``cells``).")
    lowest_t: int | None = Field(default=None, description="Index in ``cells`` of the lowest T.")
    highest_u: int | None = Field(default=None, description="Index in ``cells`` of the highest U.")
    lowest_cvar: int | None = Field(default=None, description="Index in ``cells`` of the lowest CVaR. Since 1.1.")
    p_any_below: float | None = Field(
        default=None,
        description="P(some known cell has T < tau), cells taken as independent: 1 - prod(1 - p_below). Since 1.1.",
    )
    alpha: float | None = Field(default=None, description="The level of the cells' cvar. Since 1.1.")
    tau: float | None = Field(default=None, description="The threshold of the cells' p_below. Since 1.1.")


class AnchorSetReply(Message):
    anchor_set: AnchorSet
    version: str
    instance: str | None = Field(default=None, description="The instance that answered. Since 1.2.")


class AnchorHistoryEntry(WireModel):
    accepted_at: float = Field(description="When the set became active, seconds since the Unix epoch.")
    version: str
    anchor_set: AnchorSet


class AnchorHistoryReply(Message):
    """The last accepted anchor sets of an instance, newest (the active one) first."""

    instance: str
    entries: list[AnchorHistoryEntry]


class AnchorSetRejection(Message):
    """Error reply to a rejected anchor set; the active set is unchanged."""

    errors: list[str]
    active_version: str
    instance: str | None = Field(default=None, description="The instance that refused. Since 1.2.")


class ErrorReply(Message):
    error: str


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
        description="Its first camera's learnt clock offset minus the pose stream's (service/runtime/"
        "clock_offset.py): the pose clock minus the camera's plus the links' smallest delays' difference; near 0 "
        "when both run on the robot's clock, far from 0 frames find no pose at their stamp. None: not known.",
    )
    poses_held: int = Field(default=0, description="Poses in its buffer.")
    cameras: dict[str, GridCameraStatus] = Field(default_factory=dict)
    costmap_ago_s: float | None = Field(
        default=None, description="Service seconds since the last costmap went out; None: none (or costmap off)."
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


class ExperienceStatus(WireModel):
    """The experience of an instance (docs/calibration.md): its grid, pairs and counters, open questions."""

    source: str = Field(description="The grid the outcomes belong to.")
    pairs: int = Field(description="Stored pairs, every concept tuple.")
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
