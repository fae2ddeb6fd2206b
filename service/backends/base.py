"""What the engine needs from an open-vocabulary segmentation model."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
from gcdtrav.schemas.relay import CLIPSEG_INPUT_SIDE
from numpy.typing import NDArray


class ModelUnavailableError(RuntimeError):
    """The model's weights cannot be loaded; the message says how to provide them."""


@dataclass(frozen=True)
class BackendDescription:
    """What callers (the status, the credits, `gcdtrav serve`) read of a backend, at one moment."""

    model_id: str
    input_size: tuple[int, int] = (CLIPSEG_INPUT_SIDE, CLIPSEG_INPUT_SIDE)  # (width, height) images become
    precision: str = "-"  # the mode frames run in; "-": a backend without modes
    precision_reason: str = ""  # why that mode (asked for, or what auto measured)
    measuring: bool = False  # a background measurement of the modes is running
    needs_measurement: bool = False  # auto found nothing measured: the caller should measure
    fingerprint: str = ""  # the checkpoint's (model_fingerprint), computed once at load; "": unknown


@runtime_checkable
class SegmentationBackend(Protocol):
    """Image in, one logit map per concept out. Implementations cache per-concept work themselves."""

    model_id: str

    def describe(self) -> BackendDescription:
        """Its model, input size and running mode now (the mode may change between frames)."""
        ...

    def prepare(self, concepts: Sequence[str]) -> object:
        """Per-concept work done once per anchor set (e.g. text embeddings); passed back to ``logits``."""
        ...

    def logits(self, image_rgb: NDArray[np.uint8], prepared: object) -> NDArray[np.float32]:
        """(n, h, w) float32 logits for an (H, W, 3) uint8 RGB image; (h, w) is the backend's resolution."""
        ...
