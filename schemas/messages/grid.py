"""The ground grid: the robot's pose stream in, the fused grid out."""

from __future__ import annotations

from gcdtrav.schemas.limits import MAX_FRAME_ID_CHARS, Coordinate, FiniteFloat
from gcdtrav.schemas.messages.base import Message
from gcdtrav.schemas.strict import WireModel
from pydantic import Field


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
    speed_png: bytes | None = Field(
        default=None,
        description="Fraction of the robot's maximum speed per cell (value / 65535), unknown cells included "
        '(docs/grid.md, "Speed from uncertainty"); None: the grid has no speed layer. Since 1.5.',
    )
