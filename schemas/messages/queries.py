"""Queries and their replies: a patch's or a cell's distribution, a path's cells, the anchor sets, errors."""

from __future__ import annotations

from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.messages.base import Message
from gcdtrav.schemas.strict import WireModel
from pydantic import Field


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
    accepted_at: float | None = Field(
        default=None,
        description="When the set became active in the fleet, s since the epoch (0: the start set). Present since "
        "1.5, whose services take expected=VERSION (compare-and-swap) and proposal=VERSION.",
    )


class AnchorHistoryEntry(WireModel):
    accepted_at: float = Field(description="When the set became active, seconds since the Unix epoch.")
    version: str
    anchor_set: AnchorSet
    forced: bool = Field(
        default=False, description="Applied with --force although its proposal was not judged better. Since 1.5."
    )
    activated_by: str | None = Field(default=None, description="The instance that activated it. Since 1.5.")
    how: str | None = Field(
        default=None, description="seeded, set, proposal, rollback or imported (a newer word may come). Since 1.5."
    )


class AnchorHistoryReply(Message):
    """The last accepted anchor sets of an instance, newest (the active one) first."""

    instance: str
    entries: list[AnchorHistoryEntry]


class AnchorSetRejection(Message):
    """Error reply to a rejected anchor set; the active set is unchanged."""

    errors: list[str]
    active_version: str
    instance: str | None = Field(default=None, description="The instance that refused. Since 1.2.")
    lost_to: str | None = Field(
        default=None,
        description="The version activated first while this request expected another active set: it lost the "
        "compare-and-swap. Since 1.5.",
    )


class ErrorReply(Message):
    error: str
