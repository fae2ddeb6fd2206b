"""Backend + anchor set + engine: one image in, T/U maps out. Shared by the CLI and the Zenoh service."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.config import EngineSettings
from gcdtrav.service.backends.base import SegmentationBackend
from gcdtrav.service.engine.maps import TraversabilityMaps, compute_maps
from numpy.typing import NDArray


@dataclass(frozen=True)
class ActiveAnchors:
    """An anchor set with the backend's per-concept work for it: swapped as one reference."""

    anchors: AnchorSet
    prepared: object


@dataclass(frozen=True)
class FrameResult:
    maps: TraversabilityMaps
    logits: NDArray[np.float32]
    anchors: AnchorSet  # the exact set these maps were computed with
    inference_ms: float  # backend forward only
    engine_ms: float  # softmax and statistics


class Pipeline:
    def __init__(self, backend: SegmentationBackend, anchors: AnchorSet, settings: EngineSettings) -> None:
        self.backend = backend
        self.settings = settings
        self._lock = threading.Lock()
        self._active = ActiveAnchors(anchors, backend.prepare(anchors.concepts))

    @property
    def anchors(self) -> AnchorSet:
        return self._active.anchors

    def prepare(self, anchors: AnchorSet) -> ActiveAnchors:
        """The slow part of a swap (text embeddings), done while frames keep flowing."""
        return ActiveAnchors(anchors, self.backend.prepare(anchors.concepts))

    def activate(self, active: ActiveAnchors) -> None:
        """Replace the reference (atomic): a frame in flight keeps the set it started with."""
        with self._lock:
            self._active = active

    def swap_anchors(self, anchors: AnchorSet) -> None:
        self.activate(self.prepare(anchors))

    def process(self, image_rgb: NDArray[np.uint8]) -> FrameResult:
        active = self._active  # read once: the whole frame uses one anchor set
        start = time.perf_counter()
        logits = self.backend.logits(image_rgb, active.prepared)
        inferred = time.perf_counter()
        maps = compute_maps(logits, active.anchors, self.settings)
        done = time.perf_counter()
        return FrameResult(
            maps=maps,
            logits=logits,
            anchors=active.anchors,
            inference_ms=(inferred - start) * 1e3,
            engine_ms=(done - inferred) * 1e3,
        )
