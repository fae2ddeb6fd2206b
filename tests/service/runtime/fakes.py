"""Zenoh-free stand-ins for the runtime's unit tests: a backend of deterministic logits, processed frames."""

from __future__ import annotations

import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.schemas.config import EngineSettings
from gcdtrav.schemas.images import encode_png
from gcdtrav.schemas.inputs import DecodedFrame
from gcdtrav.schemas.keys import Keys
from gcdtrav.schemas.messages import CreditGrant, MapsMessage
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.backends.base import BackendDescription
from gcdtrav.service.pipeline import Pipeline
from gcdtrav.service.runtime.assembly import Runtime
from gcdtrav.service.runtime.frames import InferredFrame, PendingFrame, ProcessedFrame
from gcdtrav.service.runtime.history import FrameHistory
from gcdtrav.service.runtime.outputs import Output
from gcdtrav.service.store import open_store
from numpy.typing import NDArray

MAP_SIDE = 8


def until(condition: Callable[[], bool], timeout_s: float = 60.0) -> None:
    """Wait for a thread of the runtime to make ``condition`` true; the bound only ends a failure."""
    deadline = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.005)
    assert condition()


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
        self.release: threading.Event | None = None  # set it to an Event: each frame waits for it first

    def describe(self) -> BackendDescription:
        return BackendDescription(self.model_id)

    def prepare(self, concepts: Sequence[str]) -> object:
        return len(concepts)

    def logits(self, image_rgb: NDArray[np.uint8], prepared: object) -> NDArray[np.float32]:
        self.started.set()
        if self.release is not None:
            assert self.release.wait(60), "the test never released the frame"
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


class RecordingSink:
    """The outputs' sink of the assembled runtime, as the bus's FrameOutputs but recording what it is given."""

    def __init__(self, prefix: str = "gcdtrav") -> None:
        self.keys = Keys(prefix)
        self.put_by_source: list[tuple[str, list[Output]]] = []
        self.forgotten: list[str] = []
        self.closed = False  # then it refuses, as the bus's outputs do after shutdown

    def wants_compact(self, source: str) -> bool:
        return False

    def put(self, source: str, outputs: list[Output]) -> bool:
        if self.closed:
            return False
        self.put_by_source.append((source, outputs))
        return True

    def forget(self, source: str) -> None:
        self.forgotten.append(source)

    @property
    def sources(self) -> list[str]:
        """The sources whose payloads were put, in order."""
        return [source for source, _ in self.put_by_source]

    def maps(self) -> list[MapsMessage]:
        """The maps messages put, in order."""
        return [
            MapsMessage.unpack(output.payload)
            for source, outputs in self.put_by_source
            for output in outputs
            if output.key == self.keys.maps(source)
        ]


class RecordingCredits:
    """The credits' sink of the assembled runtime, recording the grants."""

    def __init__(self) -> None:
        self.grants: list[CreditGrant] = []

    def put(self, source: str, grant: CreditGrant) -> bool:
        self.grants.append(grant)
        return True

    def forget(self, source: str) -> None:
        pass


def assembled(
    settings: ServiceSettings,
    run: Pipeline | None = None,
    clock: Callable[[], float] = time.monotonic,
    owns: Callable[[str], bool] = lambda source: True,
) -> tuple[Runtime, RecordingSink, RecordingCredits]:
    """The runtime as the service assembles it (``Runtime.build``), with recording sinks instead of zenoh; its
    anchor state in a new temporary folder unless ``settings`` name one."""
    if "state_dir" not in settings.model_fields_set:
        settings = settings.model_copy(update={"state_dir": Path(tempfile.mkdtemp(prefix="gcdtrav-test-state-"))})
    sink, credits = RecordingSink(settings.prefix), RecordingCredits()
    store = open_store(settings.store, settings.state_dir, settings.prefix)  # as `gcdtrav serve` opens it
    return Runtime.build(settings, run or pipeline(), sink, credits, owns, clock=clock, store=store), sink, credits


def offer(runtime: Runtime, pending: PendingFrame, publisher: str | None = None) -> bool:
    """``pending`` offered as the bus's subscriber offers a sample: the rate check, then admission."""
    if not runtime.admission.admit(publisher):
        return False
    payload = pending.payload
    return runtime.admission.offer(
        pending.source, pending.key, len(payload), lambda: payload, pending.encoding, pending.ros, publisher
    )
