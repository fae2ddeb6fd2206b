"""Where the service spends its inference (issue 34): unchanged views reused, frames shared by need.

``ReuseSettings``: a frame whose view has not changed since the source's last inferred frame is not
inferred again; its maps are published again under the new frame's stamp. ``ScheduleSettings``: which
source's frame is inferred next. Both strict (unknown fields are errors); docs/architecture.md, *Threads
and state*, says how they decide.
"""

from __future__ import annotations

from typing import Literal

from gcdtrav.schemas.strict import StrictModel
from pydantic import Field


class ReuseSettings(StrictModel):
    enabled: bool = Field(
        default=True,
        description="Frames whose view did not change since the source's last inferred frame publish that "
        "frame's maps again (counted unchanged) instead of being inferred; false: every frame is inferred.",
    )
    max_reuse_s: float = Field(
        default=5.0,
        gt=0,
        description="At most this long between a source's real inferences: its next frame after that is "
        "inferred, changed or not (a refresh: it yields to frames with news, within max_wait_s).",
    )
    blocks: tuple[int, int] = Field(
        default=(24, 18),
        description="(columns, rows) of the grey thumbnail's blocks the change is measured on.",
    )
    block_threshold: float = Field(
        default=0.25,
        gt=0,
        description="A block moved when its mean, in units of the thumbnail's contrast (its standard deviation, "
        "after removing the mean: exposure and gain flicker cancel), differs by more than this.",
    )
    changed_fraction: float = Field(
        default=0.01,
        ge=0,
        le=1,
        description="The view changed when more than this fraction of the blocks moved (0.01 of 24 x 18: 5 "
        "blocks); sensor noise moves none.",
    )
    glance_nice: int = Field(
        default=10,
        ge=0,
        le=19,
        description="The glance thread's niceness above the service's (Linux, per thread): it then runs on the "
        "cores inference leaves idle instead of pre-empting inference's threads (measured with 8 robots: "
        "inference 6-9 % slower at 0, unchanged at 10). 0: the same priority.",
    )
    translation_m: float = Field(
        default=0.05, gt=0, description="With a pose (a grid's pose_key): moved farther than this = changed."
    )
    rotation_deg: float = Field(
        default=2.0, gt=0, description="With a pose: turned more than this = changed (turning in place counts)."
    )


class ScheduleSettings(StrictModel):
    policy: Literal["need", "round_robin"] = Field(
        default="need",
        description="need: sources share inference by weight (motion, ambiguity ahead), none waits over "
        "max_wait_s; round_robin: one frame per source in turn, whatever it shows.",
    )
    max_wait_s: float = Field(
        default=10.0,
        gt=0,
        description="A frame waiting for inference longer than this goes before any weighting (oldest first).",
    )
    base_weight: float = Field(default=0.2, gt=0, description="Weight of a still source with clear ground ahead.")
    motion_weight: float = Field(default=1.0, ge=0, description="Added at full motion (see full_speed_mps).")
    ambiguity_weight: float = Field(
        default=0.5, ge=0, description="Added at full motion when all ground ahead is ambiguous (times motion)."
    )
    full_speed_mps: float = Field(default=0.5, gt=0, description="Pose speed counted as full motion.")
    full_turn_dps: float = Field(default=30.0, gt=0, description="Pose turn rate counted as full motion.")
    full_change_per_s: float = Field(
        default=0.5,
        gt=0,
        description="Without a pose: the fraction of thumbnail blocks moving per second counted as full motion.",
    )
    ambiguous_u: float = Field(
        default=0.2, gt=0, le=0.5, description="A patch of the last map is ambiguous when U is at least this."
    )
    novel_match: float = Field(
        default=0.0,
        ge=0,
        le=1,
        description="A patch is novel when its best concept's match score is below this; 0: not used.",
    )
