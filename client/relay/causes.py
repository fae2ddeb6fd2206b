"""Why a camera's maps may be stale, as the relay can tell on the robot: no zenoh, the facts given.

Each cause has a code (``RelayHealth.causes``' keys) and a sentence saying what to check:

- ``camera_silent``: no camera frame for ``camera_silent_after_s``: the camera, its driver or its key (not
  while the robot has parked the camera: stopped on purpose, ``CameraParked``);
- ``no_instance``: frames went out without a credit after the timeout and no grant came since: no service
  instance of the prefix is reachable (not running, another prefix, the link down);
- ``service_refuses``: the service answers, but its last credit names why the frames give no maps
  (``CreditGrant.problem``: stale, undecodable, too large, ...);
- ``camera_unusable``: the relay cannot decode the camera's frames;
- ``camera_wrong_type`` (the ROS 2 node): the camera's topic is published with a type that is no image
  (or another than ``ros_message_type``), so no frame can come;
- ``camera_info_unusable`` (the ROS 2 node): the camera's CameraInfo cannot place pixels on the ground (a zero
  focal length, no size): it is not sent, and a grid of this camera fuses nothing until a good one comes;
- ``camera_clock``: the camera stamps from a clock more than ``CLOCK_NOTE_S`` off this host's. Not a cause
  of staleness any more (ages are judged by delay, ``state.CameraClock``), but said: every stamp the robot's
  consumers read is on the camera's clock.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

CAMERA_SILENT, NO_INSTANCE, SERVICE_REFUSES = "camera_silent", "no_instance", "service_refuses"
CAMERA_UNUSABLE, CAMERA_CLOCK = "camera_unusable", "camera_clock"
CAMERA_WRONG_TYPE, CAMERA_INFO_UNUSABLE = "camera_wrong_type", "camera_info_unusable"
CLOCK_NOTE_S = 1.0  # the service warns of a source's clock beyond this too (clock_offset.py WARN_OFFSET_S)
TEXT_MATTERS = (
    SERVICE_REFUSES,
    CAMERA_UNUSABLE,
    CAMERA_WRONG_TYPE,
    CAMERA_INFO_UNUSABLE,
)  # a new text is a new cause; the others' texts hold figures


@dataclass(frozen=True)
class CameraFacts:
    """What the relay knows of one camera at one moment."""

    camera_key: str
    silent_s: float  # since its last frame, or since the relay started before any
    captured: int
    unanswered: int  # frames sent without a credit since the last grant
    refusal: str | None  # the last credit's problem
    unusable: str | None  # why the last camera frame could not be sent
    clock_offset_s: float | None  # this host's clock minus the camera's
    parked: bool = False  # the robot stopped the camera on purpose: its silence is no cause


def causes(facts: CameraFacts, silent_after_s: float, prefix: str) -> dict[str, str]:
    found: dict[str, str] = {}
    if facts.silent_s > silent_after_s and not facts.parked:
        since = "since the relay started" if facts.captured == 0 else f"for {facts.silent_s:.0f} s"
        found[CAMERA_SILENT] = f"no camera frame on '{facts.camera_key}' {since}: check the camera and its key"
    if facts.unanswered:
        found[NO_INSTANCE] = (
            f"{facts.unanswered} frame(s) sent without a credit, none granted since: no gcdtrav instance of prefix "
            f"'{prefix}' answers (is it running, on this prefix, and the link up?)"
        )
    if facts.refusal:
        found[SERVICE_REFUSES] = f"the service gives no maps: {facts.refusal}"
    if facts.unusable:
        found[CAMERA_UNUSABLE] = facts.unusable
    offset = facts.clock_offset_s
    if offset is not None and abs(offset) > CLOCK_NOTE_S:
        side = "behind" if offset > 0 else "ahead of"
        found[CAMERA_CLOCK] = (
            f"the camera's stamps are {abs(offset):.1f} s {side} this host's clock: map ages are judged by delay, "
            "not by this clock; stamps the robot reads are the camera's"
        )
    return found


def change_key(found: Mapping[str, str]) -> dict[str, str]:
    """What makes a change worth a log line: the codes, and the text where it is not a figure that moves."""
    return {code: text if code in TEXT_MATTERS else "" for code, text in found.items()}
