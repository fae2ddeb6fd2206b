"""``experience:`` and ``ask:``: traversal outcomes, their pairs with earlier predictions, calibration, and
questions to an operator (docs/calibration.md)."""

from __future__ import annotations

from gcdtrav.schemas.experience import MAX_OUTCOME_RADIUS_M
from gcdtrav.schemas.strict import StrictModel
from pydantic import Field, field_validator, model_validator


class TrackingSettings(StrictModel):
    """How outcomes are measured (schemas/outcomes.py), by the service's experience and by a relay on the robot
    (``outcomes:`` of its settings): the same fields, the same defaults."""

    footprint_m: float = Field(default=0.6, gt=0, le=2 * MAX_OUTCOME_RADIUS_M, description="Robot width, m.")
    min_command_mps: float = Field(
        default=0.1, ge=0, description="Only commands faster than this are graded (a robot told to stop is not slow)."
    )
    command_timeout_s: float = Field(default=0.5, gt=0, description="A command older than this is not in force.")
    outcome_spacing_m: float = Field(
        default=0.3, gt=0, description="One velocity outcome per this distance driven: the mean score over it."
    )
    outcome_period_s: float = Field(
        default=2.0, gt=0, description="At the latest this long after the last one (a robot that barely moves)."
    )


class ExperienceSettings(TrackingSettings):
    """``experience:``: traversal outcomes, their pairs with earlier predictions, calibration (docs/calibration.md)."""

    enabled: bool = Field(default=False, description="Collect outcomes and pairs; off: nothing changes.")
    cmd_vel: str | None = Field(
        default=None,
        description="Velocity commands: a zenoh key (Twist2D, msgpack or JSON) or a ROS topic starting with '/' "
        "(geometry_msgs/msg/Twist CDR).",
    )
    odometry: str | None = Field(
        default=None,
        description="Odometry: a zenoh key (Odometry2D, msgpack or JSON) or a ROS topic starting with '/' "
        "(nav_msgs/msg/Odometry CDR).",
    )
    grid: str | None = Field(default=None, description="The grid (its source) the outcomes belong to [the first].")
    lookahead_s: float = Field(
        default=2.0,
        ge=0,
        description="Outcomes pair with the cell's mixture as it stood this long before: from frames taken while "
        "the cell lay ahead, not under the robot.",
    )
    late_s: float = Field(
        default=30.0,
        ge=0,
        le=3600,
        description="An outcome arriving up to this long after its stamp still finds the prediction it pairs with "
        "(a relay's batches, a link that was down for a while): snapshots are kept for lookahead_s + late_s, within "
        "snapshot_budget_mb. Later ones are counted ignored_no_prediction.",
    )
    snapshot_every_s: float = Field(default=0.25, gt=0, description="Grid snapshots kept for the pairing, apart.")
    snapshot_budget_mb: float = Field(default=64, gt=0, description="Bytes of grid snapshots kept, MB.")
    max_pairs: int = Field(default=50_000, ge=1, description="Pairs kept, all concept tuples; the oldest go first.")
    max_bytes: int = Field(default=16_000_000, ge=1024, description="Bytes of stored pairs (their file).")
    max_age_days: float | None = Field(
        default=None,
        gt=0,
        description="Raw pairs appended longer ago go (calibration's sums stay); none: only max_pairs and "
        "max_bytes bound them.",
    )
    min_pairs_per_anchor: float = Field(
        default=20, ge=0, description="Fits hold anchors with less weight mass than this near the current set."
    )
    held_out_fraction: float = Field(default=0.3, gt=0, lt=1, description="The latest pairs, kept out of fits.")
    sample_per_source: int = Field(
        default=5_000,
        ge=1,
        description="Fits use a uniform sample of each source's whole history, this many pairs per source and "
        "concept tuple (kept after the raw pairs go).",
    )
    max_robot_share: float = Field(
        default=0.25,
        gt=0,
        le=1,
        description="At most this share of the pairs graded or fitted comes from one robot (a source's first "
        "chunk): a larger robot's pairs are sampled down. Fewer robots than 1/share: equal shares. 1: no cap.",
    )

    @model_validator(mode="after")
    def _sources_given(self) -> ExperienceSettings:
        if self.enabled and (self.cmd_vel is None) != (self.odometry is None):
            raise ValueError("experience: give both cmd_vel and odometry (or neither: outcomes from the bus only)")
        return self


class AskSettings(StrictModel):
    """``ask:``: when cells ahead stay ambiguous or novel, ask an operator (docs/calibration.md)."""

    enabled: bool = False
    range_m: float = Field(default=4.0, gt=0, description="How far ahead along the heading (or path) to look, m.")
    width_m: float = Field(default=1.0, gt=0, description="Width of the corridor ahead, m.")
    persist_s: float = Field(default=2.0, ge=0, description="Cells must stay ambiguous or novel this long.")
    u_band: tuple[float, float] = Field(default=(0.2, 1.0), description="U in [low, high] is ambiguous.")
    p_below_band: tuple[float, float] = Field(default=(0.3, 0.7), description="P(T < tau) in [low, high] is ambiguous.")
    min_match: float = Field(default=0.2, ge=0, le=1, description="A fused match score below this is novel.")
    min_cells: int = Field(default=3, ge=1, description="Cells that must persist before asking.")
    min_interval_s: float = Field(default=30.0, ge=0, description="At most one question per source this often.")
    answer_timeout_s: float = Field(default=300.0, gt=0, description="An unanswered question closes after this.")
    path_timeout_s: float = Field(
        default=5.0, gt=0, description="A planner's path (planned_path) unrenewed this long: the heading again."
    )

    @field_validator("u_band", "p_below_band")
    @classmethod
    def _band(cls, value: tuple[float, float]) -> tuple[float, float]:
        if not 0.0 <= value[0] <= value[1]:
            raise ValueError(f"band {value} must be [low, high] with 0 <= low <= high")
        return value
