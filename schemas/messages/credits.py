"""The link to a robot: a credit tells its relay the service is ready for the next frame; the relay's health
says what it knows of a camera. The credit words are defined here, once: the runtime's rooms that free a
slot (intake, triage, the fleet's ledger) import them from here."""

from __future__ import annotations

from gcdtrav.schemas.messages.base import Message
from pydantic import Field

# What freed a source's slot (CreditGrant.reason), each with what it means for the robot.
TAKEN, UNCHANGED, REFRESH, STALE, REFUSED = "taken", "unchanged", "refresh", "stale", "refused"
SUPERSEDED = "superseded"
CREDIT_REASONS = {
    TAKEN: "the frame went to inference",
    UNCHANGED: "not inferred, its view had not changed: the last maps went out again",
    REFRESH: "an unchanged view past max_reuse_s waits for inference; later unchanged frames are answered meanwhile",
    STALE: "older than max_frame_age_s",
    REFUSED: "rejected at intake",
    SUPERSEDED: "judged unchanged, but newer maps of a view it does not match went out before its answer: dropped",
}


class CreditGrant(Message):
    """The source's owner freed the source's slot: the relay may send its next frame (docs/messages.md)."""

    source: str
    instance: str = Field(description="The instance that owns the source and granted this credit.")
    grant: int = Field(description="Credits this instance granted the source so far, from 0.")
    reason: str = Field(
        description="What freed the slot: "
        + ", ".join(f"'{word}' ({meaning})" for word, meaning in CREDIT_REASONS.items())
        + ". A newer writer may send another word: read it as a credit all the same."
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
    safe_mask: str | None = Field(
        default=None,
        description="While the relay's own safe speed mask is in force (the service went quiet, or its mask "
        "arrived late; client/relay/mask_guard.py), why; None: the live mask or none. Since 1.6.",
    )


class CameraParked(Message):
    """{prefix}/relay/{source}/parked, on the robot's bus: the robot's own software says it stops (parked: true)
    or restarts (false) a camera on purpose; the relay marks its RelayHealth until told otherwise."""

    parked: bool = Field(description="True: the camera is stopped on purpose; false: it runs again.")
    reason: str = Field(default="", max_length=200, description="Why, for the operator (e.g. 'charging').")
