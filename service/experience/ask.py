"""Asking an operator when the ground ahead stays ambiguous or novel (docs/calibration.md, "Asking").

Each grid update, the cells within ``range_m`` ahead of the robot, in a corridor ``width_m`` wide along its
heading (or along a planner's path), are flagged *ambiguous* (U or P(T < tau) inside its band) or *novel*
(fused match score below ``min_match``). A cell flagged for ``persist_s`` on end (grid stamps) persists;
``min_cells`` persistent cells, no question open and none asked within ``min_interval_s`` make a question:
the region, the two concepts with the most weight there, a small crop of the last image (a callable the
wiring supplies), the stamp. An answer becomes ``operator`` outcomes for those cells, paired with the
weights the question showed, and closes the question; an unanswered one expires after
``answer_timeout_s``. Everything is counted (``counts``).

A question's id is unique across the fleet and across restarts: the source, a random part drawn when the
asker starts, and the asker's count (``robot/cam-9f3a61c2-1``). Several instances ask about one grid as it
moves between them, and each counts from 1: ids of the count alone named three regions ``robot/cam-1``.
"""

from __future__ import annotations

import itertools
import math
import secrets
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.experience import (
    OperatorAnswer,
    OperatorQuestion,
    QuestionConcept,
    TraversalOutcome,
)
from gcdtrav.schemas.messages import Pose2D
from gcdtrav.schemas.settings import AskSettings
from gcdtrav.service.engine import gcd, risk
from gcdtrav.service.grid.fusion import GroundGrid
from numpy.typing import NDArray

Region = tuple[float, float, float, float]
Crop = Callable[[Region], bytes | None]  # the region (x0, y0, x1, y1) in the grid frame -> a JPEG, or None


@dataclass(frozen=True)
class OpenQuestion:
    message: OperatorQuestion
    weights: NDArray[np.float32]  # (cells, n): what the question showed, over ``anchors``
    anchors: AnchorSet


@dataclass(frozen=True)
class Answered:
    """An answer's outcomes (one per cell, kind operator) and the predictions they pair with."""

    outcomes: list[TraversalOutcome]
    weights: NDArray[np.float32]
    anchors: AnchorSet


def corridor(
    centres_x: NDArray[np.floating],
    centres_y: NDArray[np.floating],
    pose: Pose2D,
    range_m: float,
    width_m: float,
    path: list[tuple[float, float]] | None = None,
) -> NDArray[np.bool_]:
    """Cells ahead: along the heading within range_m and width_m / 2 of its line, or within width_m / 2 of the
    path's polyline and range_m of the robot."""
    dx, dy = centres_x - pose.x, centres_y - pose.y
    if path is None or len(path) < 2:
        along = dx * math.cos(pose.yaw) + dy * math.sin(pose.yaw)
        lateral = -dx * math.sin(pose.yaw) + dy * math.cos(pose.yaw)
        return np.asarray((along > 0) & (along <= range_m) & (np.abs(lateral) <= width_m / 2))
    near = np.zeros(centres_x.shape, bool)
    for (x0, y0), (x1, y1) in itertools.pairwise(path):
        sx, sy = x1 - x0, y1 - y0
        length2 = sx * sx + sy * sy or 1e-12
        t = np.clip(((centres_x - x0) * sx + (centres_y - y0) * sy) / length2, 0, 1)
        near |= np.hypot(centres_x - (x0 + t * sx), centres_y - (y0 + t * sy)) <= width_m / 2
    return np.asarray(near & (np.hypot(dx, dy) <= range_m))


class OperatorAsker:
    """One grid's questions. Thread-safe: grid updates from the worker, answers from zenoh."""

    def __init__(self, source: str, settings: AskSettings, tau: float) -> None:
        self.source, self.settings, self.tau = source, settings, tau
        self._first_flagged: dict[tuple[int, int], tuple[float, str]] = {}  # world cell -> (since, reason)
        self._open: OpenQuestion | None = None
        self._last_asked: float | None = None
        self._asked = 0
        self._id_part = secrets.token_hex(4)  # this asker's, so that no other instance or start repeats its ids
        self._lock = threading.Lock()
        self.counts: dict[str, int] = {}

    def _count(self, name: str) -> None:
        self.counts[name] = self.counts.get(name, 0) + 1

    @property
    def open_question(self) -> OperatorQuestion | None:
        with self._lock:
            return self._open.message if self._open is not None else None

    def update(
        self, grid: GroundGrid, pose: Pose2D, crop: Crop | None = None, path: list[tuple[float, float]] | None = None
    ) -> OperatorQuestion | None:
        """Track the cells ahead after a grid update; a new question, or None."""
        s = self.settings
        if grid.anchors is None or grid.stamp is None:
            return None
        stamp, r, n = grid.stamp, grid.spec.resolution_m, grid.spec.cells
        jj, ii = np.meshgrid(np.arange(n), np.arange(n))
        centres_x, centres_y = grid.origin[0] + (jj + 0.5) * r, grid.origin[1] + (ii + 0.5) * r
        ahead = corridor(centres_x, centres_y, pose, s.range_m, s.width_m, path) & grid.known & (grid.mass > 0)
        rows, cols = np.nonzero(ahead)
        weights = (grid.weight_sums[:, rows, cols] / grid.mass[rows, cols][None, :]).astype(np.float32)
        anchors = grid.anchors
        match = grid.match()[rows, cols]
        flags = self._flags(weights, anchors, match)
        keys = [
            (math.floor(centres_x[i, j] / r), math.floor(centres_y[i, j] / r)) for i, j in zip(rows, cols, strict=True)
        ]
        with self._lock:
            self._expire(stamp)
            # A cell that stops being flagged (or leaves the corridor) starts over.
            self._first_flagged = {
                key: (self._first_flagged.get(key, (stamp, reason))[0], reason)
                for key, reason in zip(keys, flags, strict=True)
                if reason
            }
            persistent = [
                k for k, key in enumerate(keys) if flags[k] and stamp - self._first_flagged[key][0] >= s.persist_s
            ]
            if len(persistent) < s.min_cells:
                return None
            if self._open is not None:
                return None
            if self._last_asked is not None and stamp - self._last_asked < s.min_interval_s:
                self._count("rate_limited")
                return None
            self._asked += 1
            self._last_asked = stamp
            self._count("asked")
            question = self._question(
                stamp, anchors, weights[:, persistent], [flags[k] for k in persistent],
                centres_x[rows[persistent], cols[persistent]], centres_y[rows[persistent], cols[persistent]], r,
            ).model_copy(update={"match": float(np.nanmean(match[persistent]))})  # fmt: skip
            self._open = OpenQuestion(question, weights[:, persistent].T.copy(), anchors)
        if crop is not None:
            question = question.model_copy(update={"crop_jpeg": crop(question.region)})
            with self._lock:
                if self._open is not None and self._open.message.id == question.id:
                    self._open = OpenQuestion(question, self._open.weights, self._open.anchors)
        return question

    def _flags(self, weights: NDArray[np.float32], anchors: AnchorSet, match: NDArray[np.float32]) -> list[str]:
        s = self.settings
        if weights.shape[1] == 0:
            return []
        positions, widths = anchors.positions, anchors.widths
        _, u = gcd.mixture_mean_std(weights, positions, widths)
        below = risk.p_below(weights, positions, widths, self.tau)
        ambiguous = ((u >= s.u_band[0]) & (u <= s.u_band[1])) | (
            (below >= s.p_below_band[0]) & (below <= s.p_below_band[1])
        )
        novel = np.nan_to_num(match, nan=1.0) < s.min_match
        return ["novel" if nv else "ambiguous" if amb else "" for nv, amb in zip(novel, ambiguous, strict=True)]

    def _question(
        self,
        stamp: float,
        anchors: AnchorSet,
        weights: NDArray[np.float32],
        reasons: list[str],
        xs: NDArray[np.floating],
        ys: NDArray[np.floating],
        r: float,
    ) -> OperatorQuestion:
        mean = weights.mean(axis=1)
        top = np.argsort(-mean, kind="stable")[:2]
        t, u = gcd.mixture_mean_std(weights, anchors.positions, anchors.widths)
        below = risk.p_below(weights, anchors.positions, anchors.widths, self.tau)
        return OperatorQuestion(
            id=f"{self.source}-{self._id_part}-{self._asked}"[-64:],  # the unique tail kept
            source=self.source,
            stamp=stamp,
            reason="novel" if reasons.count("novel") * 2 > len(reasons) else "ambiguous",
            region=(float(xs.min() - r / 2), float(ys.min() - r / 2), float(xs.max() + r / 2), float(ys.max() + r / 2)),
            cells=[(round(float(x), 6), round(float(y), 6)) for x, y in zip(xs, ys, strict=True)],
            concepts=[
                QuestionConcept(concept=anchors.concepts[k], position=anchors.positions[k], weight=float(mean[k]))
                for k in top
            ],
            traversability=float(t.mean()),
            uncertainty=float(u.mean()),
            p_below=float(below.mean()),
            anchor_set_version=anchors.version,
        )

    def _expire(self, stamp: float) -> None:
        if self._open is not None and stamp - self._open.message.stamp > self.settings.answer_timeout_s:
            self._open = None
            self._count("expired")

    def answer(self, answer: OperatorAnswer, received_at: float) -> Answered:
        """The outcomes of an answer to the open question (which it closes); ValueError for another id."""
        with self._lock:
            question = self._open
            if question is None or question.message.id != answer.id or answer.source != self.source:
                self._count("unknown_answer")
                open_id = question.message.id if question is not None else "none"
                raise ValueError(f"no open question '{answer.id}' for source '{answer.source}' (open: {open_id})")
            self._open = None
            self._count("answered")
        stamp = answer.stamp if answer.stamp is not None else received_at
        outcomes = [
            TraversalOutcome(stamp=stamp, x=x, y=y, score=answer.score, kind="operator")
            for x, y in question.message.cells
        ]
        return Answered(outcomes, question.weights, question.anchors)
