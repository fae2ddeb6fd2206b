"""From logits to the T and U maps with the configured method."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.config import EngineSettings, Method
from gcdtrav.service.engine import gcd
from gcdtrav.service.engine.novelty import match_score
from numpy.typing import NDArray


@dataclass(frozen=True)
class TraversabilityMaps:
    """T and U at the backend's resolution, with the weights they came from (anchors on axis 0) and each
    patch's match score (the best concept's own probability, before the softmax: low where no anchor fits)."""

    traversability: NDArray[np.float32]
    uncertainty: NDArray[np.float32]
    weights: NDArray[np.float32]
    match: NDArray[np.float32]


def compute_maps(logits: NDArray[np.floating], anchors: AnchorSet, settings: EngineSettings) -> TraversabilityMaps:
    if logits.ndim < 2 or logits.shape[0] != len(anchors):
        raise ValueError(f"logits of shape {logits.shape} do not match an anchor set of {len(anchors)} anchors")
    positions = np.asarray(anchors.positions, np.float32)
    if settings.method is Method.GCD:
        weights, t, u = gcd.softmax_mean_std(logits, positions, anchors.widths, settings.temperature)
        if settings.normalize_uncertainty:
            u /= np.float32(max(gcd.max_mixture_std(anchors.positions, anchors.widths), 1e-12))
    else:
        weights = gcd.softmax_weights(logits, settings.temperature)
        baseline = gcd.argmax_baseline if settings.method is Method.ARGMAX else gcd.gaussian_fit_baseline
        t, u = baseline(weights, positions)
    if not (np.isfinite(t).all() and np.isfinite(u).all()):
        # A NaN or +inf logit (or a patch of only -inf) turns its patch's softmax, hence T or U, into NaN;
        # checking the maps instead of the logits saves a pass over the largest array. A lone -inf is weight 0.
        raise ValueError("logits contain NaN or infinity")
    return TraversabilityMaps(traversability=t, uncertainty=u, weights=weights, match=match_score(logits))
