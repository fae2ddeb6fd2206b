"""What the engine needs from an open-vocabulary segmentation model."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray


class ModelUnavailableError(RuntimeError):
    """The model's weights cannot be loaded; the message says how to provide them."""


@runtime_checkable
class SegmentationBackend(Protocol):
    """Image in, one logit map per concept out. Implementations cache per-concept work themselves."""

    model_id: str

    def prepare(self, concepts: Sequence[str]) -> object:
        """Per-concept work done once per anchor set (e.g. text embeddings); passed back to ``logits``."""
        ...

    def logits(self, image_rgb: NDArray[np.uint8], prepared: object) -> NDArray[np.float32]:
        """(n, h, w) float32 logits for an (H, W, 3) uint8 RGB image; (h, w) is the backend's resolution."""
        ...
