"""The risk measures' defaults (docs/risk.md)."""

from __future__ import annotations

from gcdtrav.schemas.strict import StrictModel
from pydantic import Field


class RiskSettings(StrictModel):
    """The risk measures' defaults, for answers whose query names none (docs/risk.md)."""

    alpha: float = Field(
        default=0.1, gt=0, le=1, description="CVaR and quantile level: the worst alpha of the distribution."
    )
    tau: float = Field(
        default=0.3, ge=0, le=1, description="p_below = P(T < tau): the traversability too low to drive."
    )
