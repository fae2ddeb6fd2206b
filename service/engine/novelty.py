"""How well the best concept matches a patch, before the softmax hides it.

The softmax over anchors says which concept wins, not whether any concept fits: a patch of something no
anchor names still gets weights summing to 1. CLIPSeg's logits are per-concept binary-segmentation logits
(each concept is segmented on its own), so sigmoid(logit_k) is concept k's own probability of covering
the patch, and the best of them says whether the anchor set describes the patch at all.
"""

from __future__ import annotations

import numpy as np
from gcdtrav.service.engine.gcd import FloatArray
from numpy.typing import NDArray


def match_score(logits: FloatArray) -> NDArray[np.float32]:
    """sigmoid(max_k logit_k) per patch: near 0 where no concept matches (novel), near 1 where one does.

    Logits have the anchors on axis 0 and any patch layout after it; the result has the patch layout.
    Monotone in the best logit; float32 rounds it to exactly 1 above a logit of about 16.6 and to 0 below
    about -88.7. A NaN logit gives NaN.
    """
    scores = np.asarray(logits, dtype=np.float32)
    if scores.ndim < 1 or scores.shape[0] < 1:
        raise ValueError(f"logits need the anchors on axis 0, got shape {scores.shape}")
    best = scores.max(axis=0)
    with np.errstate(over="ignore"):  # exp(-best) overflows to inf for best < -88: the score is then 0
        return np.asarray(1.0 / (1.0 + np.exp(-best)), dtype=np.float32)
