"""What each cell of a ground grid predicted a moment ago: a bounded ring of snapshots of the fused weights.

An outcome at time t pairs with the cell's mixture as it stood at t - lookahead_s, from frames taken while
the cell lay ahead of the robot, not from the frames that saw it under the robot's bumper. A snapshot holds
only the known cells (float16 weights, their flat indices), the grid's origin (it scrolls) and the anchor
set the weights were fused with; one is taken at most every ``every_s`` (by the grid's stamps), and the
ring keeps at most ``budget_bytes`` of them, the oldest going first, and none older than needed.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass

import numpy as np
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.service.grid.fusion import GroundGrid
from numpy.typing import NDArray


@dataclass(frozen=True)
class Snapshot:
    stamp: float
    origin: tuple[float, float]
    resolution: float
    cells: int  # the grid is cells x cells
    anchors: AnchorSet
    known: NDArray[np.int32]  # flat indices (i * cells + j) of the known cells, ascending
    weights: NDArray[np.float16]  # (len(known), n): each known cell's normalised weights

    @property
    def nbytes(self) -> int:
        return int(self.known.nbytes + self.weights.nbytes)

    def cells_near(self, x: float, y: float, radius: float | None) -> NDArray[np.int64]:
        """Flat indices of the cells whose centre lies within ``radius`` of (x, y) (the cell of (x, y) for
        None or a radius smaller than a cell), inside the grid."""
        r, n = self.resolution, self.cells
        j0, i0 = int(np.floor((x - self.origin[0]) / r)), int(np.floor((y - self.origin[1]) / r))
        if radius is None or radius < r / 2:
            inside = 0 <= i0 < n and 0 <= j0 < n
            return np.array([i0 * n + j0] if inside else [], np.int64)
        reach = int(np.ceil(radius / r)) + 1
        ii, jj = np.meshgrid(
            np.arange(i0 - reach, i0 + reach + 1), np.arange(j0 - reach, j0 + reach + 1), indexing="ij"
        )
        cx, cy = self.origin[0] + (jj + 0.5) * r, self.origin[1] + (ii + 0.5) * r
        near = (np.hypot(cx - x, cy - y) <= radius) & (ii >= 0) & (ii < n) & (jj >= 0) & (jj < n)
        return np.asarray(ii[near] * n + jj[near], np.int64)

    def weights_at(self, flat: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.float32]]:
        """Of the given cells, those known here, and their weights."""
        where = np.searchsorted(self.known, flat)
        where = np.minimum(where, max(len(self.known) - 1, 0))
        known = (len(self.known) > 0) & (self.known[where] == flat) if len(self.known) else np.zeros(len(flat), bool)
        return flat[known], self.weights[where[known]].astype(np.float32)

    def centre(self, flat: int) -> tuple[float, float]:
        i, j = divmod(int(flat), self.cells)
        return self.origin[0] + (j + 0.5) * self.resolution, self.origin[1] + (i + 0.5) * self.resolution


def take_snapshot(grid: GroundGrid) -> Snapshot | None:
    """The grid's known cells now; None before its first frame."""
    if grid.anchors is None or grid.stamp is None:
        return None
    known = grid.known & (grid.mass > 0)
    flat = np.flatnonzero(known).astype(np.int32)
    sums = grid.weight_sums.reshape(grid.weight_sums.shape[0], -1)[:, flat]
    weights = (sums / grid.mass.reshape(-1)[flat][None, :]).T.astype(np.float16)
    return Snapshot(grid.stamp, grid.origin, grid.spec.resolution_m, grid.spec.cells, grid.anchors, flat, weights)


class SnapshotRing:
    """The recent snapshots of one grid. Thread-safe: frames capture, outcomes look up."""

    def __init__(self, every_s: float, budget_bytes: int, keep_s: float) -> None:
        self.every_s, self.budget_bytes, self.keep_s = every_s, budget_bytes, keep_s
        self._ring: deque[Snapshot] = deque()
        self._bytes = 0
        self._lock = threading.Lock()

    @property
    def nbytes(self) -> int:
        return self._bytes

    def __len__(self) -> int:
        return len(self._ring)

    def capture(self, grid: GroundGrid) -> bool:
        """Snapshot the grid if ``every_s`` passed since the last one (grid stamps); whether it did."""
        with self._lock:
            last = self._ring[-1].stamp if self._ring else None
        if grid.stamp is None or (last is not None and grid.stamp - last < self.every_s and grid.stamp >= last):
            return False
        snapshot = take_snapshot(grid)
        if snapshot is None:
            return False
        with self._lock:
            if self._ring and snapshot.stamp < self._ring[-1].stamp:  # a replayed bag restarted: begin anew
                self._ring.clear()
                self._bytes = 0
            self._ring.append(snapshot)
            self._bytes += snapshot.nbytes
            while (
                self._ring
                and (self._bytes > self.budget_bytes or self._ring[0].stamp < snapshot.stamp - self.keep_s)
                and len(self._ring) > 1
            ):
                self._bytes -= self._ring.popleft().nbytes
        return True

    def before(self, stamp: float) -> Snapshot | None:
        """The newest snapshot taken at or before ``stamp``."""
        with self._lock:
            for snapshot in reversed(self._ring):
                if snapshot.stamp <= stamp:
                    return snapshot
        return None
