"""Learning from the robot's own driving (issue 33, docs/calibration.md): traversal outcomes in, calibration
figures, fitted anchor proposals and operator questions out. Wire messages follow the wire rule
(``WireModel``: unknown fields ignored); the settings sections ``experience:`` and ``ask:`` are in
``schemas/settings/experience.py``.
"""

from __future__ import annotations

import math
from typing import Literal

from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.limits import MAX_CONCEPT_CHARS, MAX_FRAME_ID_CHARS, Coordinate, FiniteFloat
from gcdtrav.schemas.messages import Message, MessageError
from gcdtrav.schemas.strict import WireModel
from pydantic import ConfigDict, Field, field_validator

OutcomeKind = Literal["velocity", "operator", "contact"]
OUTCOME_KINDS: tuple[str, ...] = ("velocity", "operator", "contact")
MAX_OUTCOME_RADIUS_M = 10.0  # a footprint, not a region: larger would pair thousands of cells per outcome
CALIBRATION_ALPHAS = (0.05, 0.1, 0.2)


# ---- outcomes in --------------------------------------------------------------------------------------


class TraversalOutcome(Message):
    """How driving over a place went: {prefix}/in/{source}/outcome, {source} the grid's."""

    stamp: FiniteFloat = Field(description="When the robot was there, s since the epoch (the grid's clock).")
    x: Coordinate = Field(description="Metres in the grid's frame (the pose stream's odometry frame).")
    y: Coordinate
    score: FiniteFloat = Field(description="1 = drove as commanded, 0 = could not move at all; in [0, 1].")
    kind: OutcomeKind = Field(description="velocity (tracking), operator (an answer), contact (bumper, stall).")
    radius_m: float | None = Field(
        default=None, description="Every cell whose centre lies within this radius, m; None: the cell of (x, y)."
    )

    @field_validator("stamp")
    @classmethod
    def _not_negative(cls, value: float) -> float:
        if value < 0:
            raise ValueError(f"stamp {value} is before the epoch")
        return value

    @field_validator("score")
    @classmethod
    def _in_unit_interval(cls, value: float) -> float:
        if not 0.0 <= value <= 1.0:
            raise ValueError(f"score {value} is outside [0, 1] (1 = drove as commanded)")
        return value

    @field_validator("radius_m")
    @classmethod
    def _radius(cls, value: float | None) -> float | None:
        if value is not None and not (math.isfinite(value) and 0.0 <= value <= MAX_OUTCOME_RADIUS_M):
            raise ValueError(f"radius_m {value} must be in [0, {MAX_OUTCOME_RADIUS_M:g}] m")
        return value


MAX_BATCH_OUTCOMES = 1000  # a batch a second holds a few: 1000 is a relay that could not send for minutes


class OutcomeBatch(Message):
    """Outcomes measured on the robot by its relay (schemas/outcomes.py), sent together at most every
    ``outcomes.batch_period_s``: {prefix}/in/{source}/outcomes, {source} the grid's. Since 1.6."""

    outcomes: list[TraversalOutcome] = Field(max_length=MAX_BATCH_OUTCOMES)
    sent_at: FiniteFloat = Field(description="The robot's clock when the batch left, s since the epoch.")
    dropped: int = Field(
        default=0, ge=0, description="Outcomes the relay dropped since its last batch: more than a batch holds."
    )

    @classmethod
    def decode_each(cls, payload: bytes, max_bytes: int | None = None) -> tuple[OutcomeBatch, int]:
        """The batch with each outcome validated alone, and how many were left out: an outcome this reader does
        not take (a kind a newer relay added, a value out of range) costs only itself, not the batch's other
        outcomes. MessageTooLarge, MessageError when the batch itself is not one (not a map, too many)."""
        data = cls.fields(payload, max_bytes)
        items = data.get("outcomes")
        if not isinstance(items, list) or len(items) > MAX_BATCH_OUTCOMES:
            return cls.validated(data), 0  # the batch's own error
        batch = cls.validated({**data, "outcomes": []})
        kept: list[TraversalOutcome] = []
        for item in items:
            try:
                if isinstance(item, dict):
                    kept.append(TraversalOutcome.validated(item))
            except MessageError:
                continue
        return batch.model_copy(update={"outcomes": kept}), len(items) - len(kept)


class Twist2D(Message):
    """A velocity command in msgpack or JSON (the zenoh form of geometry_msgs/Twist): base frame, m/s, rad/s."""

    stamp: float | None = Field(default=None, description="Command time; None: when received.")
    vx: FiniteFloat
    vy: FiniteFloat = 0.0
    wz: FiniteFloat = 0.0


class Odometry2D(Message):
    """Pose and velocity in msgpack or JSON (the zenoh form of nav_msgs/Odometry): velocities in the base frame."""

    stamp: FiniteFloat
    frame_id: str = Field(default="odom", max_length=MAX_FRAME_ID_CHARS)
    x: Coordinate
    y: Coordinate
    yaw: FiniteFloat = 0.0
    vx: FiniteFloat
    vy: FiniteFloat = 0.0
    wz: FiniteFloat = 0.0


MAX_PATH_POINTS = 10_000  # a planner's path: a few hundred points; 10k bounds the corridor's work per update


class PlannedPath(Message):
    """A planner's path ahead on {prefix}/in/{source}/planned_path: where to look for ground worth asking about
    (``ask.range_m`` of it, ``ask.width_m`` wide) instead of along the heading. Each replaces the last; an empty
    one, or none for ``ask.path_timeout_s``, means the heading again."""

    stamp: FiniteFloat = Field(description="When planned, s since the epoch (the planner's clock; not compared).")
    frame_id: str = Field(default="odom", max_length=MAX_FRAME_ID_CHARS, description="The grid's frame.")
    points: list[tuple[Coordinate, Coordinate]] = Field(
        max_length=MAX_PATH_POINTS, description="(x, y) of the path's vertices from the robot on, metres."
    )


# ---- calibration ---------------------------------------------------------------------------------------


class ReliabilityBin(WireModel):
    low: float = Field(description="The bin covers predicted P(T < tau) in [low, high).")
    high: float
    count: int
    predicted: float | None = Field(description="Mean predicted P(T < tau) of the bin's pairs; None if empty.")
    observed: float | None = Field(description="Share of the bin's outcomes below tau; None if empty.")


class AnchorFigures(WireModel):
    concept: str = Field(max_length=MAX_CONCEPT_CHARS)
    position: float
    width: float
    weight_mass: float = Field(description="Sum of this anchor's weight over the pairs (pair-equivalents).")
    dominant_pairs: int = Field(description="Pairs where this anchor has the largest weight.")
    dominant_mean_outcome: float | None = Field(description="Mean outcome of those pairs; None if none.")


class CalibrationFigures(WireModel):
    """The figures of docs/calibration.md for one anchor set over one set of pairs; None where undefined."""

    pairs: int
    mae: float | None = Field(description="Mean |T - outcome|.")
    bias: float | None = Field(description="Mean (T - outcome): > 0 means T promises more than the robot got.")
    coverage: dict[str, float | None] = Field(
        description="Per alpha ('0.05', '0.1', '0.2'): share of outcomes >= q_alpha; calibrated: 1 - alpha."
    )
    tau: float
    reliability: list[ReliabilityBin]
    ece: float | None = Field(description="Expected calibration error of P(T < tau) over the bins.")
    ause: float | None = Field(description="Area under the sparsification error of U against |T - outcome|.")
    spearman_u_error: float | None = Field(description="Spearman's rho of U against |T - outcome|.")
    anchors: list[AnchorFigures]


class CalibrationReport(Message):
    """{prefix}/out/{source}/calibration: the active anchor set graded by the stored experience."""

    source: str
    stamp: float = Field(description="When the report was computed, s since the epoch.")
    anchor_set_version: str
    concepts: list[str] = Field(description="The concept tuple whose pairs are graded (other tuples are apart).")
    figures: CalibrationFigures
    pairs_by_kind: dict[str, int] = Field(default_factory=dict)
    pairs_by_version: dict[str, int] = Field(
        default_factory=dict, description="Stored pairs by the anchor-set version that made their prediction."
    )
    counts: dict[str, int] = Field(
        default_factory=dict, description="The store's counters: outcomes, pairs, rejected and ignored by reason."
    )
    pairs_by_source: dict[str, int] = Field(
        default_factory=dict, description="The graded pairs by the grid (robot) they came from, the fleet's. Since 1.5."
    )
    by_source: dict[str, CalibrationFigures] | None = Field(
        default=None, description="Each source's own figures, when asked (by_source=true); else None. Since 1.5."
    )
    share_by_robot: dict[str, float] = Field(
        default_factory=dict,
        description="Each robot's share of the graded pairs, after the cap (experience.max_robot_share). Since 1.7.",
    )
    excluded_robots: list[str] = Field(
        default_factory=list, description="Robots whose pairs an operator excluded (not graded). Since 1.7."
    )


# ---- anchor proposals -----------------------------------------------------------------------------------


class AnchorChange(WireModel):
    concept: str = Field(max_length=MAX_CONCEPT_CHARS)
    position_before: float | None = Field(description="None: the concept is new.")
    position_after: float | None = Field(description="None: the concept is removed.")
    width_before: float | None
    width_after: float | None
    pairs: float = Field(description="The anchor's weight mass in the training pairs (pair-equivalents).")
    shrunk: bool = Field(description="Held near the current set: too few pairs to move it freely.")


FigureJudgement = Literal["better", "same", "worse", "undefined"]
Verdict = Literal["better", "no better", "worse"]
MIN_HELD_OUT_PAIRS = 200  # below this, a difference of the figures is noise (docs/calibration.md, "Verdicts")
# A figure moves "better" or "worse" only by more than its tolerance: smaller moves are noise on a few hundred
# correlated pairs (one outcome pairs every cell of the robot's footprint).
TOLERANCES: dict[str, float] = {"mae": 0.01, "coverage shortfall": 0.02, "ece": 0.01}


def coverage_shortfall(figures: CalibrationFigures) -> float | None:
    """How far the worst q_alpha covers below its promise 1 - alpha (0: every quantile kept its promise; a set
    that covers more than promised is not penalised: its atoms count whole). None without coverage."""
    gaps = [(1 - float(alpha)) - cover for alpha, cover in figures.coverage.items() if cover is not None]
    return max(0.0, *gaps) if gaps else None


class FigureVerdict(WireModel):
    figure: str = Field(description="mae, coverage shortfall or ece: smaller is better for each.")
    before: float | None
    after: float | None
    # A plain string on the wire (FigureJudgement's words today): a word a newer service adds must not make
    # this reader refuse the whole proposal.
    judgement: str


class BaselineJudgement(WireModel):
    """The proposed set against another set than the current one, on the same held-out pairs."""

    baseline: str = Field(description='Which set: "paper\'s set" or "best in history".')
    version: str
    verdict: str = Field(description="better | no better | worse: the proposed set against this one.")
    figures: list[FigureVerdict]


class ProposalVerdict(WireModel):
    """A proposal judged on its held-out pairs: better only if no judged figure is worse and one is better, and
    (since 1.5) not worse than the paper's set or the best set of the history either."""

    verdict: str = Field(description="Verdict's words today; any other word (a newer service) is never applied.")
    figures: list[FigureVerdict]
    held_out_pairs: int
    min_held_out_pairs: int = MIN_HELD_OUT_PAIRS
    enough_pairs: bool
    against: list[BaselineJudgement] = Field(
        default_factory=list,
        description="The proposed set against the paper's set and the history's best of the same concepts; a "
        "worse judgement against any makes the verdict worse. Since 1.5.",
    )

    @property
    def applicable(self) -> bool:
        """What `gcdtrav anchors propose --apply` swaps in without --force."""
        return self.verdict == "better" and self.enough_pairs

    def reason(self) -> str:
        """One line: the verdict, the figures behind it, the pairs."""
        worse_here = _verdict(self.figures) == "worse"  # against the current set (the baselines come below)
        shown = [f for f in self.figures if f.judgement == "worse"] if worse_here else self.figures
        figures = ", ".join(f"{f.figure} {_figure(f.before)} -> {_figure(f.after)} ({f.judgement})" for f in shown)
        pairs = f"{self.held_out_pairs} held-out pairs"
        if not self.enough_pairs:
            pairs += f", fewer than the {self.min_held_out_pairs} a verdict needs"
        worse_than = [
            f"worse than the {b.baseline} {b.version} ("
            + ", ".join(
                f"{f.figure} {_figure(f.before)} -> {_figure(f.after)}" for f in b.figures if f.judgement == "worse"
            )
            + ")"
            for b in self.against
            if b.verdict == "worse"
        ]
        if worse_than:
            figures = "; ".join(worse_than) + (f"; against the current set: {figures}" if figures else "")
        return f"{self.verdict} on the held-out pairs: {figures or 'no figure defined'}; {pairs}"


def _figure(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"


def _judge(figure: str, before: float | None, after: float | None) -> FigureVerdict:
    judgement: FigureJudgement = "undefined"
    if before is not None and after is not None:
        change, tolerance = after - before, TOLERANCES[figure]
        judgement = "better" if change < -tolerance else "worse" if change > tolerance else "same"
    return FigureVerdict(figure=figure, before=before, after=after, judgement=judgement)


def judge_proposal(
    before: CalibrationFigures, after: CalibrationFigures, held_out_pairs: int, min_pairs: int = MIN_HELD_OUT_PAIRS
) -> ProposalVerdict:
    """The current set's held-out figures against the proposed set's, on MAE, coverage and ECE."""
    figures = _judged_figures(before, after)
    return ProposalVerdict(
        verdict=_verdict(figures),
        figures=figures,
        held_out_pairs=held_out_pairs,
        min_held_out_pairs=min_pairs,
        enough_pairs=held_out_pairs >= min_pairs,
    )


def _judged_figures(before: CalibrationFigures, after: CalibrationFigures) -> list[FigureVerdict]:
    return [
        _judge("mae", before.mae, after.mae),
        _judge("coverage shortfall", coverage_shortfall(before), coverage_shortfall(after)),
        _judge("ece", before.ece, after.ece),
    ]


def _verdict(figures: list[FigureVerdict]) -> Verdict:
    judgements = {f.judgement for f in figures}
    return "worse" if "worse" in judgements else "better" if "better" in judgements else "no better"


def judge_against(
    verdict: ProposalVerdict, after: CalibrationFigures, baselines: list[tuple[str, str, CalibrationFigures]]
) -> ProposalVerdict:
    """``verdict`` (the proposed set against the current one) also against each (name, version, figures)
    baseline on the same held-out pairs: worse against any makes it worse, since a set that only beats a
    worse current one (a forced set) is no improvement of what the fleet had."""
    against = []
    for name, version, figures in baselines:
        judged = _judged_figures(figures, after)
        against.append(BaselineJudgement(baseline=name, version=version, verdict=_verdict(judged), figures=judged))
    worse = verdict.verdict == "worse" or any(b.verdict == "worse" for b in against)
    return verdict.model_copy(update={"against": against, "verdict": "worse" if worse else verdict.verdict})


class AnchorProposal(Message):
    """{prefix}/config/anchors/proposal: a fitted anchor set, applied only by an operator."""

    stamp: float
    source: str = Field(default="", description="Whose experience it was fitted on ('' for offline fits).")
    current: AnchorSet
    proposed: AnchorSet
    current_version: str
    proposed_version: str
    diff: list[str] = Field(description="The +/-/~ lines `gcdtrav anchors set --dry-run` prints.")
    changes: list[AnchorChange]
    train_pairs: int
    held_out_pairs: int
    before: CalibrationFigures = Field(description="The current set on the held-out (later) pairs.")
    after: CalibrationFigures = Field(description="The proposed set on the same pairs.")
    verdict: ProposalVerdict | None = Field(
        default=None, description="judge_proposal of before and after; None from a service older than verdicts."
    )
    kept: bool = Field(
        default=False,
        description="Kept in the fleet's store under proposed_version: `gcdtrav anchors apply VERSION` applies "
        "exactly this proposed set, never a refit. False: an offline fit, or a service before 1.5.",
    )
    pairs_from: float | None = Field(default=None, description="The first pair's stamp, s. Since 1.5.")
    pairs_until: float | None = Field(
        default=None, description="The last pair's stamp, s: pairs that came later are not in it. Since 1.5."
    )
    share_by_robot: dict[str, float] = Field(
        default_factory=dict,
        description="Each robot's share of the pairs fitted and judged, after the cap. Since 1.7.",
    )
    excluded_robots: list[str] = Field(
        default_factory=list, description="Robots whose pairs an operator excluded (not used). Since 1.7."
    )

    def judged(self) -> ProposalVerdict:
        """The service's verdict, or (an older service sent none) the same judgement made here from the figures,
        which every version sends."""
        return self.verdict or judge_proposal(self.before, self.after, self.held_out_pairs)


# ---- exclusions --------------------------------------------------------------------------------------


class ExclusionRequest(Message):
    """{prefix}/config/experience/exclusions (a query's payload): exclude a robot's pairs from calibration and
    fits, or include them again. A robot is a source's first chunk (``r7`` for r7/front). Since 1.7."""

    robot: str = Field(pattern=r"^[^/*$#?]+$", max_length=64, description="The robot: a source's first chunk.")
    excluded: bool = True
    actor: str = Field(default="", max_length=200, description="Who asks (kept with the word).")
    reason: str = Field(default="", max_length=500)


class ExclusionWord(WireModel):
    robot: str
    excluded: bool
    at: float = Field(description="When it was said, s since the epoch.")
    actor: str
    reason: str
    instance: str = Field(description="The instance that recorded it.")


class ExclusionList(Message):
    """The reply: the word in force per robot (excluded, or included again), by robot. Since 1.7."""

    words: list[ExclusionWord] = Field(default_factory=list)

    @property
    def excluded(self) -> list[str]:
        return [w.robot for w in self.words if w.excluded]


class KeptSource(WireModel):
    source: str
    pairs: int
    bytes: int = Field(description="Their bytes as the bounds count them (records.pair_bytes).")
    oldest: float = Field(description="When the oldest kept pair was appended, s since the epoch (0: before 1.7).")
    newest: float


class StoreContents(Message):
    """{prefix}/config/experience/kept: what the fleet's store keeps (`gcdtrav kept`). Since 1.7."""

    backend: str
    location: str
    pairs: int
    bytes: int
    max_pairs: int
    max_bytes: int
    max_age_days: float | None = None
    sources: list[KeptSource] = Field(default_factory=list)
    graded: dict[str, int] = Field(
        default_factory=dict,
        description="Calibration sums kept (they outlive the raw pairs): pairs graded per version@tau.",
    )


# ---- asking the operator -----------------------------------------------------------------------------


class QuestionConcept(WireModel):
    concept: str = Field(max_length=MAX_CONCEPT_CHARS)
    position: float
    weight: float = Field(description="Mean weight over the region's cells.")


class OperatorQuestion(Message):
    """{prefix}/out/{source}/question: cells ahead stayed ambiguous or novel for ask.persist_s."""

    # The crop is binary: base64 in JSON (a query with format=json), raw bytes in msgpack.
    model_config = ConfigDict(ser_json_bytes="base64", val_json_bytes="base64")

    id: str = Field(max_length=64)
    source: str
    stamp: float = Field(description="Grid stamp when the question was asked.")
    reason: Literal["ambiguous", "novel"]
    region: tuple[float, float, float, float] = Field(description="(x0, y0, x1, y1) in the grid's frame, m.")
    cells: list[tuple[float, float]] = Field(description="Centres of the region's cells, m.")
    concepts: list[QuestionConcept] = Field(description="The two competing concepts, strongest first.")
    traversability: float | None = Field(default=None, description="Mean T over the region.")
    uncertainty: float | None = Field(default=None, description="Mean U over the region.")
    p_below: float | None = Field(default=None, description="Mean P(T < tau) over the region.")
    match: float | None = Field(default=None, description="Mean match score over the region.")
    anchor_set_version: str
    crop_jpeg: bytes | None = Field(default=None, description="A small JPEG of the region from the last image.")


class OperatorAnswer(Message):
    """An operator's answer to a question: drivable (1), blocked (0) or a score."""

    id: str = Field(max_length=64)
    source: str
    score: float
    stamp: float | None = Field(default=None, description="When answered; None: when received.")
    operator: str = Field(default="", max_length=MAX_FRAME_ID_CHARS)

    @field_validator("score")
    @classmethod
    def _in_unit_interval(cls, value: float) -> float:
        if not (math.isfinite(value) and 0.0 <= value <= 1.0):
            raise ValueError(f"score {value} is outside [0, 1] (1 = drivable, 0 = blocked)")
        return value


class AnswerReply(Message):
    """The reply to an answer sent as a query on {prefix}/in/{source}/answer."""

    id: str = Field(max_length=64)
    source: str
    score: float
    pairs: int = Field(description="Pairs the answer's operator outcomes made (one per cell of the question).")


ANSWER_WORDS: dict[str, float] = {"drivable": 1.0, "blocked": 0.0}


def answer_score(text: str) -> float:
    """`gcdtrav answer SOURCE drivable|blocked|SCORE` -> the score; ValueError with the accepted forms."""
    if text in ANSWER_WORDS:
        return ANSWER_WORDS[text]
    try:
        score = float(text)
    except ValueError:
        raise ValueError(f"answer '{text}': give drivable, blocked or a score in [0, 1]") from None
    if not 0.0 <= score <= 1.0:
        raise ValueError(f"answer {score}: a score must be in [0, 1]")
    return score
