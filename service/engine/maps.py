"""From logits to the T and U maps with the configured method."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.config import EngineSettings, Method
from gcdtrav.service.engine import gcd
from numpy.typing import NDArray


@dataclass(frozen=True)
class TraversabilityMaps:
    """T and U at the backend's resolution, with the weights they came from (anchors on axis 0)."""

    traversability: NDArray[np.float32]
    uncertainty: NDArray[np.float32]
    weights: NDArray[np.float32]


def compute_maps(logits: NDArray[np.floating], anchors: AnchorSet, settings: EngineSettings) -> TraversabilityMaps:
    if logits.ndim < 2 or logits.shape[0] != len(anchors):
        raise ValueError(f"logits of shape {logits.shape} do not match an anchor set of {len(anchors)} anchors")
    if not np.all(np.isfinite(logits)):
        raise ValueError("logits contain NaN or infinity")
    weights = gcd.softmax_weights(logits, settings.temperature)
    positions = np.asarray(anchors.positions, np.float32)
    if settings.method is Method.ARGMAX:
        t, u = gcd.argmax_baseline(weights, positions)
    elif settings.method is Method.GAUSSIAN:
        t, u = gcd.gaussian_fit_baseline(weights, positions)
    else:
        t, u = gcd.mixture_mean_std(weights, positions, np.asarray(anchors.widths, np.float32))
        if settings.normalize_uncertainty:
            u = u / np.float32(max(gcd.max_mixture_std(anchors.positions, anchors.widths), 1e-12))
    return TraversabilityMaps(traversability=t, uncertainty=u, weights=weights)
