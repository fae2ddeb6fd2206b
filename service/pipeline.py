"""Backend + anchor set + engine: one image in, T/U maps out. Shared by the CLI and the Zenoh service."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.config import EngineSettings, Method
from gcdtrav.service.backends.base import BackendDescription, SegmentationBackend
from gcdtrav.service.engine.maps import TraversabilityMaps, compute_maps
from numpy.typing import NDArray


@dataclass(frozen=True)
class ActiveAnchors:
    """An anchor set with the backend's per-concept work for it: swapped as one reference."""

    anchors: AnchorSet
    prepared: object


@dataclass(frozen=True)
class Inference:
    """A frame's logits, between the backend and the engine (the service runs the two in different threads)."""

    logits: NDArray[np.float32]
    anchors: AnchorSet
    inference_ms: float


@dataclass(frozen=True)
class FrameResult:
    maps: TraversabilityMaps
    logits: NDArray[np.float32]
    anchors: AnchorSet  # the exact set these maps were computed with
    method: Method  # how T and U were computed from the weights
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
        """The set the next frame runs with. In the service the AnchorSwitch owns which set is active (its
        history's head, with when it was accepted) and installs it here with ``activate``."""
        return self._active.anchors

    def describe(self) -> BackendDescription:
        """The backend's model, input size and running mode, as callers may read them."""
        return self.backend.describe()

    def prepare(self, anchors: AnchorSet) -> ActiveAnchors:
        """The slow part of a swap (text embeddings), done while frames keep flowing."""
        return ActiveAnchors(anchors, self.backend.prepare(anchors.concepts))

    def activate(self, active: ActiveAnchors) -> None:
        """Replace the reference (atomic): a frame in flight keeps the set it started with."""
        with self._lock:
            self._active = active

    def infer(self, image_rgb: NDArray[np.uint8]) -> Inference:
        """The backend's forward with the active anchor set (read once: the whole frame uses one set)."""
        active = self._active
        start = time.perf_counter()
        logits = self.backend.logits(image_rgb, active.prepared)
        return Inference(logits, active.anchors, (time.perf_counter() - start) * 1e3)

    def finish(self, inference: Inference) -> FrameResult:
        """Logits to T and U with the anchor set the logits were computed for."""
        start = time.perf_counter()
        maps = compute_maps(inference.logits, inference.anchors, self.settings)
        return FrameResult(
            maps=maps,
            logits=inference.logits,
            anchors=inference.anchors,
            method=self.settings.method,
            inference_ms=inference.inference_ms,
            engine_ms=(time.perf_counter() - start) * 1e3,
        )

    def process(self, image_rgb: NDArray[np.uint8]) -> FrameResult:
        return self.finish(self.infer(image_rgb))


def clipseg_pipeline(
    model: str | None,
    precision: str,
    anchors: AnchorSet,
    engine: EngineSettings,
    cache_dir: Path | None = None,
    measure_now: bool = True,
) -> Pipeline:
    """The one assembly of CLIPSeg and the engine, for `gcdtrav infer` and `gcdtrav serve`: ``model`` a
    directory or hub id (None: $GCDTRAV_MODEL, else CIDAS/clipseg-rd64-refined); ``cache_dir`` where the
    ONNX exports and auto's measurement live (None: the user's cache); ``measure_now`` False: auto with
    nothing cached starts in fp32 and leaves the measurement to the caller."""
    from gcdtrav.service.backends import default_model
    from gcdtrav.service.backends.clipseg import ClipSegBackend

    backend = ClipSegBackend(
        model or default_model(), precision=precision, cache_dir=cache_dir, measure_now=measure_now
    )
    return Pipeline(backend, anchors, engine)
