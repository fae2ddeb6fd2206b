"""The patch/region distribution query over the frame history. No middleware here.

Query parameters (zenoh selector parameters, all strings):
  x, y      image pixel          | i, j   map patch (row, column)  | region=x0,y0,x1,y1 image pixels
  seq       a kept frame's sequence number [default: the latest]
  stamp     a kept frame's input stamp (s since epoch, e.g. a ROS header stamp), matched within 1 ms
  alpha     level of quantile and cvar, in (0, 1] [settings risk.alpha]
  tau       threshold of p_below, in [0, 1] [settings risk.tau]
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.messages import AnchorPoint, ContextDistribution
from gcdtrav.schemas.settings import RiskSettings
from gcdtrav.service.engine import gcd, risk
from gcdtrav.service.runtime.errors import QueryError
from gcdtrav.service.runtime.history import FrameHistory, FrameRecord
from numpy.typing import NDArray


def parse_number(text: str, name: str, kind: type = float) -> float:
    """A finite number from a query parameter, or a QueryError that names the parameter."""
    try:
        value = kind(text)
    except ValueError:
        raise QueryError(f"parameter {name}='{text}' is not a{' whole' if kind is int else ''} number") from None
    if not math.isfinite(value):
        raise QueryError(f"parameter {name}='{text}' is not finite")
    return value


def _number(params: Mapping[str, str], name: str, kind: type = float) -> float:
    return parse_number(params[name], name, kind)


def _patch_of_pixel(record: FrameRecord, x: float, y: float) -> tuple[int, int]:
    width, height = record.image_size
    if not (0 <= x < width and 0 <= y < height):
        raise QueryError(f"pixel ({x:g}, {y:g}) is outside the {width}x{height} image")
    sx, sy = record.scale
    h, w = record.map_shape
    return min(int(y / sy), h - 1), min(int(x / sx), w - 1)


def _region_cells(record: FrameRecord, text: str) -> tuple[int, int, int, int]:
    try:
        x0, y0, x1, y1 = (float(v) for v in text.split(","))
    except ValueError:
        raise QueryError(f"region='{text}' must be x0,y0,x1,y1 in image pixels") from None
    width, height = record.image_size
    if not (0 <= x0 < x1 <= width and 0 <= y0 < y1 <= height):
        raise QueryError(f"region ({text}) must satisfy 0 <= x0 < x1 <= {width} and 0 <= y0 < y1 <= {height}")
    sx, sy = record.scale
    h, w = record.map_shape
    i0, j0 = min(int(y0 / sy), h - 1), min(int(x0 / sx), w - 1)
    i1, j1 = max(min(math.ceil(y1 / sy), h), i0 + 1), max(min(math.ceil(x1 / sx), w), j0 + 1)
    return i0, j0, i1, j1


RISK_PARAMETERS = {"alpha", "tau"}
KNOWN_PARAMETERS = {"x", "y", "i", "j", "seq", "stamp", "region"} | RISK_PARAMETERS
PATCH_FORMS = (
    "x=..;y=.. (image pixels), i=..;j=.. (map patch) or region=x0,y0,x1,y1, and optionally seq=.. or stamp=.., "
    "alpha=.. (0 < alpha <= 1), tau=.. (0 <= tau <= 1)"
)


@dataclass(frozen=True)
class RiskLevels:
    """The alpha and tau an answer's risk measures are computed at."""

    alpha: float
    tau: float


def risk_levels(params: Mapping[str, str], defaults: RiskSettings) -> RiskLevels:
    """alpha and tau from the query's parameters, else the settings'; a clear error when out of range."""
    alpha = parse_number(params["alpha"], "alpha") if "alpha" in params else defaults.alpha
    tau = parse_number(params["tau"], "tau") if "tau" in params else defaults.tau
    if not 0 < alpha <= 1:
        raise QueryError(f"parameter alpha={alpha:g} must satisfy 0 < alpha <= 1 (the worst alpha of the distribution)")
    if not 0 <= tau <= 1:
        raise QueryError(f"parameter tau={tau:g} must satisfy 0 <= tau <= 1 (a traversability)")
    return RiskLevels(alpha, tau)


def parameter_pairs(text: str) -> list[tuple[str, str]]:
    """'a=1;b=2' -> [('a', '1'), ('b', '2')], as zenoh splits a selector's parameters; 'c' -> ('c', '')."""
    pairs = [part.split("=", 1) for part in text.split(";") if part]
    return [(pair[0], pair[1] if len(pair) == 2 else "") for pair in pairs]


def strict_parameters(pairs: Iterable[tuple[str, str]], forms: str) -> dict[str, str]:
    """Selector parameters as a mapping; a repeated or empty parameter is an error that names it."""
    params: dict[str, str] = {}
    for name, value in pairs:
        if name in params:
            raise QueryError(f"parameter '{name}' is given more than once; give each once: {forms}")
        if not value:
            raise QueryError(f"parameter '{name}' has no value; give {forms}")
        params[name] = value
    return params


def answer_patch_query(
    history: FrameHistory, source: str, params: Mapping[str, str], risk: RiskSettings | None = None
) -> ContextDistribution:
    unknown = set(params) - KNOWN_PARAMETERS
    if unknown:
        raise QueryError(f"unknown parameter(s) {sorted(unknown)}; give {PATCH_FORMS}")
    levels = risk_levels(params, risk or RiskSettings())
    seq = int(_number(params, "seq", int)) if "seq" in params else None
    stamp = _number(params, "stamp") if "stamp" in params else None
    if seq is not None and stamp is not None:
        raise QueryError("give seq or stamp, not both")
    record = history.get(source, seq, stamp)
    forms = [form for form in (("x", "y"), ("i", "j"), ("region",)) if any(p in params for p in form)]
    if len(forms) != 1 or not all(p in params for p in forms[0]):
        raise QueryError("give exactly one of: x and y (image pixels), i and j (map patch), region=x0,y0,x1,y1")
    patch: tuple[int, int] | None = None
    region: tuple[int, int, int, int] | None = None
    if forms[0] == ("x", "y"):
        patch = _patch_of_pixel(record, _number(params, "x"), _number(params, "y"))
    elif forms[0] == ("i", "j"):
        i, j = int(_number(params, "i", int)), int(_number(params, "j", int))
        h, w = record.map_shape
        if not (0 <= i < h and 0 <= j < w):
            raise QueryError(f"cell (i={i}, j={j}) is outside the {h}x{w} map")
        patch = (i, j)
    else:
        region = _region_cells(record, params["region"])
    i0, j0, i1, j1 = region if region is not None else _single(patch)
    weights = record.weights[:, i0:i1, j0:j1].astype(np.float32).mean(axis=(1, 2))
    weights /= weights.sum()  # float16 storage: renormalise
    match = float(record.match[i0:i1, j0:j1].astype(np.float32).mean()) if record.match is not None else None
    answer = distribution_of(weights, record.anchors, source, record.seq, record.stamp, record.frame_id, patch, region)
    return with_risk(answer, weights, record.anchors, levels, match)


def distribution_of(
    weights: NDArray[np.float32],
    anchors: AnchorSet,
    source: str,
    seq: int | None,
    stamp: float,
    frame_id: str = "",
    patch: tuple[int, int] | None = None,
    region: tuple[int, int, int, int] | None = None,
) -> ContextDistribution:
    """The full ContextDistribution of one weight vector over ``anchors``."""
    positions, widths = np.asarray(anchors.positions), np.asarray(anchors.widths)
    stats = gcd.mixture_statistics(weights[:, None], positions, widths)
    grid = gcd.density_grid()
    density = gcd.mixture_density(weights[:, None], positions, widths, grid)[0]
    return ContextDistribution(
        source=source,
        seq=seq,
        stamp=stamp,
        frame_id=frame_id,
        anchor_set_version=anchors.version,
        anchors=[
            AnchorPoint(concept=c, position=float(p), width=float(w))
            for c, p, w in zip(anchors.concepts, positions, widths, strict=True)
        ],
        weights=[float(v) for v in weights],
        patch=patch,
        region=region,
        mean=float(stats.mean[0]),
        std=float(stats.std[0]),
        skewness=float(stats.skewness[0]),
        excess_kurtosis=float(stats.excess_kurtosis[0]),
        entropy=float(stats.entropy[0]),
        modes=int(stats.modes[0]),
        top_anchors=[int(v) for v in stats.top_anchors[:, 0]],
        density_x=[float(v) for v in grid],
        density=[float(v) for v in density],
        density_bandwidth=gcd.DEFAULT_DENSITY_BANDWIDTH,
    )


def _single(patch: tuple[int, int] | None) -> tuple[int, int, int, int]:
    """One patch as the region of it alone."""
    assert patch is not None
    return patch[0], patch[1], patch[0] + 1, patch[1] + 1


def with_risk(
    answer: ContextDistribution,
    weights: NDArray[np.float32],
    anchors: AnchorSet,
    levels: RiskLevels,
    match: float | None = None,
) -> ContextDistribution:
    """The answer with its quantile, CVaR and P(T < tau) at ``levels`` (service/engine/risk.py), and match."""
    measures = risk.risk_measures(weights[:, None], anchors.positions, anchors.widths, levels.alpha, levels.tau)
    return answer.model_copy(
        update={
            "alpha": levels.alpha,
            "tau": levels.tau,
            "quantile": float(measures.quantile[0]),
            "cvar": float(measures.cvar[0]),
            "p_below": float(measures.p_below[0]),
            "match": match,
        }
    )
