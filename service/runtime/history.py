"""Per-source frame history for patch queries, within a byte budget. No middleware here."""

from __future__ import annotations

import threading
from collections import OrderedDict, deque
from dataclasses import dataclass

import cv2
import numpy as np
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.service.runtime.errors import QueryError
from numpy.typing import NDArray

STAMP_TOLERANCE_S = 1e-3


@dataclass(frozen=True)
class FrameRecord:
    seq: int
    stamp: float
    frame_id: str
    weights: NDArray[np.float16]  # (n, h, w): float16 halves the history's memory; ~1e-3 relative
    anchors: AnchorSet
    image_size: tuple[int, int]  # (width, height) in the camera's pixels (a relay's original_size, else the image's)
    match: NDArray[np.float16] | None = None  # (h, w): the best concept's own score per patch

    @property
    def map_shape(self) -> tuple[int, int]:
        return int(self.weights.shape[1]), int(self.weights.shape[2])

    @property
    def scale(self) -> tuple[float, float]:
        """Image pixels per patch, (sx, sy)."""
        h, w = self.map_shape
        return self.image_size[0] / w, self.image_size[1] / h


class FrameHistory:
    """The last frames of every source, for queries, within a total byte budget. Thread-safe.

    Each source keeps at most ``depth`` frames; all sources together keep at most ``budget_bytes`` of
    weights, the oldest frame (of whichever source) evicted first. Memory is bounded by the budget, not by
    the number of sources a peer invents.
    """

    def __init__(self, depth: int, budget_bytes: int | None = None) -> None:
        self.depth = depth
        self.budget_bytes = budget_bytes
        self._frames: dict[str, deque[FrameRecord]] = {}
        self._arrivals: OrderedDict[tuple[str, int], int] = OrderedDict()  # (source, seq) -> bytes, oldest first
        self._bytes = 0
        self._next_seq: dict[str, int] = {}  # outlives evicted frames; a forgotten source starts at 0 again
        self._lock = threading.Lock()

    def record(
        self,
        source: str,
        weights: NDArray[np.floating],
        anchors: AnchorSet,
        stamp: float,
        frame_id: str,
        image_size: tuple[int, int],
        match: NDArray[np.floating] | None = None,
    ) -> FrameRecord:
        """Number a processed frame (0, 1, ... per source) and keep it; returns its record."""
        with self._lock:
            seq = self._next_seq.get(source, 0)
            self._next_seq[source] = seq + 1
        kept_match = as_float16(match) if match is not None else None
        record = FrameRecord(seq, stamp, frame_id, as_float16(weights), anchors, image_size, kept_match)
        self.add(source, record)
        return record

    def add(self, source: str, record: FrameRecord) -> None:
        size = record.weights.nbytes + (record.match.nbytes if record.match is not None else 0)
        with self._lock:
            if len(self._frames.get(source, ())) >= self.depth:
                self._drop_oldest_of(source)  # may delete the source's deque (depth 1): take it afterwards
            self._frames.setdefault(source, deque()).append(record)
            self._arrivals[(source, record.seq)] = size
            self._bytes += size
            while self.budget_bytes is not None and self._bytes > self.budget_bytes and self._arrivals:
                oldest_source, _ = next(iter(self._arrivals))
                self._drop_oldest_of(oldest_source)

    def _drop_oldest_of(self, source: str) -> None:
        frames = self._frames[source]
        record = frames.popleft()
        self._bytes -= self._arrivals.pop((source, record.seq))
        if not frames:
            del self._frames[source]

    def forget(self, source: str) -> None:
        """Drop every frame of ``source`` and its numbering (an idle source whose state the service lets go)."""
        with self._lock:
            while source in self._frames:
                self._drop_oldest_of(source)
            self._next_seq.pop(source, None)

    @property
    def nbytes(self) -> int:
        with self._lock:
            return self._bytes

    def _limits(self) -> str:
        budget = f" and a budget of {self.budget_bytes / 1e6:.0f} MB for all sources" if self.budget_bytes else ""
        return f"the last {self.depth} frames per source{budget}"

    def get(self, source: str, seq: int | None, stamp: float | None = None) -> FrameRecord:
        with self._lock:
            frames = list(self._frames.get(source, ()))
        if not frames:
            raise QueryError(
                f"unknown source '{source}': no frame of it is kept (none processed yet, or evicted: the "
                f"history keeps {self._limits()}, and idle sources are forgotten)"
            )
        if stamp is not None:
            nearest = min(frames, key=lambda record: abs(record.stamp - stamp))
            if abs(nearest.stamp - stamp) > STAMP_TOLERANCE_S:
                raise QueryError(
                    f"no kept frame of '{source}' has stamp {stamp:.6f} (kept: {frames[0].stamp:.6f} "
                    f"to {frames[-1].stamp:.6f}; the history keeps {self._limits()})"
                )
            return nearest
        if seq is None:
            return frames[-1]
        for record in frames:
            if record.seq == seq:
                return record
        kept = f"{frames[0].seq}..{frames[-1].seq}"
        raise QueryError(f"seq {seq} of '{source}' is not kept (kept: {kept}; the history keeps {self._limits()})")


def as_float16(values: NDArray[np.floating]) -> NDArray[np.float16]:
    """``values.astype(np.float16)``, bit for bit, by OpenCV's vectorised conversion: numpy's converts one
    element at a time (a frame's 13 x 352 x 352 weights: 2.3 ms against 0.1-0.24 on a 2-core EPYC, on the
    inference thread of every frame)."""
    source = np.asarray(values)
    if source.dtype != np.float32 or source.ndim == 0 or source.size == 0:
        return source.astype(np.float16)  # float64 by way of float32 could round twice: numpy's cast is exact
    matrix = np.ascontiguousarray(source).reshape(-1, source.shape[-1])
    if hasattr(cv2, "convertFp16"):  # OpenCV 4: the half floats' bits, typed int16
        rows = cv2.convertFp16(matrix).view(np.float16)
    else:  # OpenCV 5 dropped it and computes in float16: adding -0.0 is the exact identity, -0.0 and NaN too
        rows = cv2.add(matrix, -0.0, dtype=cv2.CV_16F)  # type: ignore[call-overload]  # stubs: no scalar operand
    return np.asarray(rows, dtype=np.float16).reshape(source.shape)
