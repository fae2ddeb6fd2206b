"""Configuration shapes shared by the engine, the offline CLI and the service."""

from __future__ import annotations

from enum import Enum

from gcdtrav.schemas.strict import FrozenStrictModel
from pydantic import Field


class Method(str, Enum):
    """How per-patch anchor weights become T and U."""

    GCD = "gcd"  # the paper's method: mixture mean and standard deviation
    ARGMAX = "argmax"  # baseline: position of the top anchor, 1 - its weight
    GAUSSIAN = "gaussian"  # baseline: one Gaussian fitted by least squares (unimodal ablation)


class EngineSettings(FrozenStrictModel):
    """How the GCD engine turns logits into maps."""

    method: Method = Method.GCD
    temperature: float = Field(default=1.0, gt=0, description="Softmax temperature over the anchors' logits.")
    normalize_uncertainty: bool = Field(
        default=False,
        description="Divide sigma by the largest sigma the anchor set can produce, so U spans [0, 1].",
    )
