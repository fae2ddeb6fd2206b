"""Zenoh-free stand-ins for the runtime's unit tests: a backend of deterministic logits, processed frames."""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence

import numpy as np
from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.schemas.config import EngineSettings
from gcdtrav.schemas.images import encode_png
from gcdtrav.schemas.inputs import DecodedFrame
from gcdtrav.service.backends.base import BackendDescription
from gcdtrav.service.pipeline import Pipeline
from gcdtrav.service.runtime.frames import InferredFrame, PendingFrame, ProcessedFrame
from gcdtrav.service.runtime.history import FrameHistory
from numpy.typing import NDArray

MAP_SIDE = 8


class Clock:
    """A clock the test moves: it reads ``now`` (seconds)."""

    def __init__(self, now: float = 0.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


class FakeBackend:
    """Logits of an (8, 8) map that vary over patches; ``delay_s`` per frame; ``release`` gates each frame."""

    model_id = "fake"

    def __init__(self, delay_s: float = 0.0) -> None:
        self.delay_s = delay_s
        self.started = threading.Event()

    def describe(self) -> BackendDescription:
        return BackendDescription(self.model_id)

    def prepare(self, concepts: Sequence[str]) -> object:
        return len(concepts)

    def logits(self, image_rgb: NDArray[np.uint8], prepared: object) -> NDArray[np.float32]:
        self.started.set()
        time.sleep(self.delay_s)
        n = int(prepared)  # type: ignore[call-overload]
        grid = np.linspace(-2, 2, n * MAP_SIDE * MAP_SIDE, dtype=np.float32).reshape(n, MAP_SIDE, MAP_SIDE)
        return grid + float(image_rgb.mean()) / 255


def pipeline(delay_s: float = 0.0) -> Pipeline:
    return Pipeline(FakeBackend(delay_s), default_anchor_set(), EngineSettings())


def image(height: int = 48, width: int = 64) -> NDArray[np.uint8]:
    y, x = np.mgrid[0:height, 0:width]
    return np.stack([x * 4 % 256, y * 5 % 256, (x + y) % 256], axis=2).astype(np.uint8)


def png_frame(source: str = "r1/front", height: int = 48, width: int = 64) -> PendingFrame:
    return PendingFrame(source, f"gcdtrav/in/{source}", encode_png(image(height, width)), "image/png", time.time())


def processed(source: str = "r1/front", height: int = 48, width: int = 64) -> ProcessedFrame:
    """A frame through the fake pipeline and a history, as the worker hands it to the outputs."""
    run = pipeline()
    rgb = image(height, width)
    pending = png_frame(source, height, width)
    inferred = InferredFrame(pending, DecodedFrame(rgb, 12.5, "cam"), None, run.infer(rgb))
    result = run.finish(inferred.inference)
    record = FrameHistory(2).record(source, result.maps.weights, result.anchors, 12.5, "cam", (width, height))
    return ProcessedFrame(inferred, result, record)
