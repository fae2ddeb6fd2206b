"""A square grid of Gaussian Context Distributions, fused over pixels and frames with exponential forgetting.

Each cell keeps, per anchor, the sum of the anchor weights of the pixels that fell in it, and the number of
those pixels (its mass); both decay by one half every ``half_life_s``. The cell's distribution is
weight_sums / mass: the mean of its pixels' weight vectors, recent frames counting more. T, U and the rest
come from it with the same engine as the image maps. Cells never observed are unknown (NaN), not zero. The
pixels' match scores (how well the best concept fits, engine/novelty.py) are fused the same way.

Each cell also keeps the stamp it was last observed at. A cell not observed for ``max_age_s`` (by the frames'
stamps, not the wall clock) expires: it is cleared, unknown again, and counted ``expired`` until observed anew.

Index convention (as nav_msgs/OccupancyGrid): cell (row i, column j) covers
x in [origin_x + j r, origin_x + (j + 1) r) and y in [origin_y + i r, origin_y + (i + 1) r).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.service.engine import gcd
from numpy.typing import NDArray

ArrayT = TypeVar("ArrayT", bound=np.ndarray)


@dataclass(frozen=True)
class GridSpec:
    size_m: float = 20.0
    resolution_m: float = 0.1
    half_life_s: float = 2.0
    max_age_s: float | None = None  # None or 0: cells never expire

    @property
    def cells(self) -> int:
        return max(1, round(self.size_m / self.resolution_m))


class GroundGrid:
    def __init__(self, spec: GridSpec, anchor_count: int, origin: tuple[float, float] | None = None) -> None:
        self.spec = spec
        n = spec.cells
        self.origin = origin if origin is not None else (-n * spec.resolution_m / 2, -n * spec.resolution_m / 2)
        self.weight_sums = np.zeros((anchor_count, n, n), np.float32)
        self.match_sums = np.zeros((n, n), np.float32)
        self.mass = np.zeros((n, n), np.float64)
        self.count = np.zeros((n, n), np.int64)
        self.last_seen = np.full((n, n), np.nan, np.float64)  # stamp of the last frame that observed the cell
        self.expired = np.zeros((n, n), np.bool_)  # observed once, then not for max_age_s: cleared
        self.stamp: float | None = None
        # The set the weights were fused with: answers use it, not the service's active set, which may have
        # been swapped since (another count, or other concepts in the same places) until the next frame.
        self.anchors: AnchorSet | None = None
        self.resets = 0
        self.last_reset = ""

    # ---- bookkeeping ---------------------------------------------------------------------------------
    def reset(self, anchor_count: int, reason: str) -> None:
        n = self.spec.cells
        self.weight_sums = np.zeros((anchor_count, n, n), np.float32)
        self.match_sums[:] = 0
        self.mass[:] = 0
        self.count[:] = 0
        self.last_seen[:] = np.nan
        self.expired[:] = False
        self.resets += 1
        self.last_reset = reason

    def decay_to(self, stamp: float) -> None:
        if self.stamp is not None and stamp > self.stamp:
            factor = 0.5 ** ((stamp - self.stamp) / self.spec.half_life_s)
            self.weight_sums *= np.float32(factor)
            self.match_sums *= np.float32(factor)
            self.mass *= factor
        self.stamp = stamp if self.stamp is None else max(self.stamp, stamp)
        self.expire()

    def expire(self) -> int:
        """Clear the cells not observed for max_age_s before the newest stamp; how many expired now."""
        max_age = self.spec.max_age_s
        if not max_age or self.stamp is None:
            return 0
        with np.errstate(invalid="ignore"):  # NaN: never observed, never expires
            old = (self.stamp - self.last_seen > max_age) & (self.count > 0)
        if old.any():
            self.weight_sums[:, old] = 0
            self.match_sums[old] = 0
            self.mass[old] = 0
            self.count[old] = 0
            self.expired |= old
        return int(old.sum())

    def index_of(self, x: NDArray[np.floating], y: NDArray[np.floating]) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        r = self.spec.resolution_m
        return (
            np.floor((np.asarray(y) - self.origin[1]) / r).astype(np.intp),
            np.floor((np.asarray(x) - self.origin[0]) / r).astype(np.intp),
        )

    def centre_of(self, i: int, j: int) -> tuple[float, float]:
        r = self.spec.resolution_m
        return round(self.origin[0] + (j + 0.5) * r, 9), round(self.origin[1] + (i + 0.5) * r, 9)

    # ---- fusion --------------------------------------------------------------------------------------
    def add(
        self,
        points: NDArray[np.floating],
        weights: NDArray[np.floating],
        stamp: float,
        anchors: AnchorSet,
        match: NDArray[np.floating] | None = None,
    ) -> int:
        """Fuse pixel weights (n, P) over ``anchors`` and match scores (P,) at ground points (P, 2); returns
        the pixels that landed. Without match scores the pixels count as matched (1)."""
        if weights.shape[0] != len(anchors):
            raise ValueError(f"{weights.shape[0]} weight rows for an anchor set of {len(anchors)}")
        if self.anchors is not None and anchors.version != self.anchors.version:
            self.reset(weights.shape[0], f"anchor set changed from {self.anchors.version} to {anchors.version}")
        elif self.weight_sums.shape[0] != weights.shape[0]:
            self.reset(weights.shape[0], "number of anchors changed")
        self.anchors = anchors
        self.decay_to(stamp)
        i, j = self.index_of(points[:, 0], points[:, 1])
        n = self.spec.cells
        inside = (i >= 0) & (i < n) & (j >= 0) & (j < n)
        flat = i[inside] * n + j[inside]
        landed = np.bincount(flat, minlength=n * n).reshape(n, n)
        self.mass += landed
        self.count += landed
        seen = landed > 0
        self.last_seen[seen] = np.fmax(self.last_seen[seen], stamp)  # fmax: NaN (never seen) loses
        self.expired[seen] = False
        scores = np.ones(int(inside.sum())) if match is None else np.asarray(match, np.float64)[inside]
        self.match_sums += np.bincount(flat, weights=scores, minlength=n * n).reshape(n, n).astype(np.float32)
        sums = self.weight_sums.reshape(weights.shape[0], -1)
        for k in range(weights.shape[0]):  # one bincount per anchor: vectorised over the pixels
            sums[k] += np.bincount(flat, weights=weights[k, inside], minlength=n * n).astype(np.float32)
        return int(inside.sum())

    def scroll_to(self, origin: tuple[float, float]) -> None:
        """Move the grid by whole cells, keeping what overlaps; cells that enter are unknown."""
        r = self.spec.resolution_m
        dj = round((origin[0] - self.origin[0]) / r)
        di = round((origin[1] - self.origin[1]) / r)
        if dj == 0 and di == 0:
            return
        self.origin = (self.origin[0] + dj * r, self.origin[1] + di * r)
        self.weight_sums = _shift(self.weight_sums, di, dj)
        self.match_sums = _shift(self.match_sums, di, dj)
        self.mass = _shift(self.mass, di, dj)
        self.count = _shift(self.count, di, dj)
        self.last_seen = _shift(self.last_seen, di, dj, fill=np.nan)
        self.expired = _shift(self.expired, di, dj)

    # ---- reading -------------------------------------------------------------------------------------
    @property
    def known(self) -> NDArray[np.bool_]:
        return self.count > 0

    def distributions(self) -> NDArray[np.float32]:
        """(n, N, N) normalised weights; NaN where unknown."""
        mass = np.where(self.mass > 0, self.mass, np.nan).astype(np.float32)
        weights = self.weight_sums / mass[None]
        weights[:, ~self.known] = np.nan
        return weights

    def layers(
        self, positions: NDArray[np.floating], widths: NDArray[np.floating]
    ) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[Any]]:
        """T and U of every cell (NaN where unknown) and the observation counts."""
        weights = self.distributions()
        known = self.known
        t = np.full(known.shape, np.nan, np.float32)
        u = np.full(known.shape, np.nan, np.float32)
        if known.any():
            mean, std = gcd.mixture_mean_std(weights[:, known], positions, widths)
            t[known], u[known] = mean, std
        return t, u, self.count.copy()

    def match(self) -> NDArray[np.float32]:
        """The fused match score of every cell (mean of its pixels', recent frames counting more); NaN where
        unknown."""
        out = np.full(self.mass.shape, np.nan, np.float32)
        known = self.known & (self.mass > 0)
        out[known] = self.match_sums[known] / self.mass[known]
        return out

    def age(self) -> NDArray[np.float64]:
        """Seconds from each cell's last observation to the newest stamp; NaN where never observed (expired
        cells keep their age)."""
        if self.stamp is None:
            return np.full(self.last_seen.shape, np.nan)
        return self.stamp - self.last_seen

    def cell_match(self, i: int, j: int) -> float | None:
        """One cell's fused match score (``match()``'s); None where unknown."""
        if not (self.known[i, j] and self.mass[i, j] > 0):
            return None
        return float(self.match_sums[i, j] / self.mass[i, j])

    def cell_weights(self, i: int, j: int) -> NDArray[np.float32] | None:
        if not self.known[i, j]:
            return None
        return (self.weight_sums[:, i, j] / np.float32(self.mass[i, j])).astype(np.float32)

    def path_cells(self, points: list[tuple[float, float]]) -> list[tuple[int, int]]:
        """Cells along a polyline, sampled every resolution, each once, in order; outside cells left out."""
        r = self.spec.resolution_m
        cells: list[tuple[int, int]] = []
        n = self.spec.cells
        for (x0, y0), (x1, y1) in itertools.pairwise(points):
            steps = max(1, math.ceil(math.hypot(x1 - x0, y1 - y0) / r))
            for s in range(steps + 1):
                x, y = x0 + (x1 - x0) * s / steps, y0 + (y1 - y0) * s / steps
                i, j = (int(v) for v in self.index_of(np.array(x), np.array(y)))
                if 0 <= i < n and 0 <= j < n and (not cells or cells[-1] != (i, j)) and (i, j) not in cells:
                    cells.append((i, j))
        return cells


def _shift(array: ArrayT, di: int, dj: int, fill: float = 0) -> ArrayT:
    """``out[..., i, j] = array[..., i + di, j + dj]``, ``fill`` where that falls outside."""
    out = np.full_like(array, fill)
    n_i, n_j = array.shape[-2:]
    src_i = slice(max(di, 0), n_i + min(di, 0))
    dst_i = slice(max(-di, 0), n_i + min(-di, 0))
    src_j = slice(max(dj, 0), n_j + min(dj, 0))
    dst_j = slice(max(-dj, 0), n_j + min(-dj, 0))
    if src_i.start < src_i.stop and src_j.start < src_j.stop:
        out[..., dst_i, dst_j] = array[..., src_i, src_j]
    return out
