"""A frame's record on its way through the service: it arrives (callback), is inferred (first worker) and
processed (second worker). Each stage keeps the one before it, so nothing is copied or re-wrapped."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from gcdtrav.schemas.inputs import DecodedFrame
from gcdtrav.service.pipeline import FrameResult, Inference
from gcdtrav.service.ros.cdr import RosTopic
from gcdtrav.service.runtime.grids.encoding import FusedGrid
from gcdtrav.service.runtime.history import FrameRecord


@dataclass(frozen=True)
class PendingFrame:
    """As it arrived: queued by the subscriber callback, latest-only per source."""

    source: str
    key: str
    payload: bytes
    encoding: str
    received_at: float
    ros: RosTopic | None = None  # set for CDR payloads from ROS 2 inputs
    stamp: float | None = None  # capture, read at intake without decoding (None: a bare image, or unreadable)
    sent_at: float | None = None  # the envelope's sent_at (a relay's clock), echoed in the credit
    lag_s: float | None = None  # judged at intake (service/runtime/intake/freshness.py); None: no usable stamp

    @property
    def times(self) -> FrameTimes:
        return FrameTimes(self.stamp, self.sent_at, self.received_at)


@dataclass(frozen=True)
class FrameTimes:
    """The times of a frame that freed its source's slot, echoed in the credit so the sender can time the link."""

    stamp: float | None  # capture, the sender's clock
    sent_at: float | None  # the envelope's sent_at, the sender's clock
    received_at: float  # this service's clock


@dataclass(frozen=True)
class InferredFrame:
    """Decoded and through the backend; the engine's part runs next, possibly on the output thread."""

    pending: PendingFrame
    image: DecodedFrame
    ros_header: Any  # the ROS message header to reuse on ROS outputs, or None
    inference: Inference


@dataclass(frozen=True)
class ProcessedFrame:
    """T and U computed, numbered, kept in the history and fused into its ground grid: what every output is
    encoded from."""

    inferred: InferredFrame
    result: FrameResult
    record: FrameRecord
    grid: FusedGrid | None = None  # the grid this frame's camera feeds, just fused; None: none, or not fused

    @property
    def pending(self) -> PendingFrame:
        return self.inferred.pending

    @property
    def source(self) -> str:
        return self.inferred.pending.source

    @property
    def image(self) -> DecodedFrame:
        return self.inferred.image
