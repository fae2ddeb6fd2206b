"""No single robot steers the fleet's experience (issue 58, docs/calibration.md "Whose experience").

A robot is the first chunk of a source (``r7`` for ``r7`` and ``r7/front``: the identity that may put under
those keys, schemas/access.py). Calibration, fits and their judgement use the pairs of robots not excluded by
an operator, each robot's share of them capped at ``max_share``: a robot holding more has a uniform sample of
its pairs kept, as many as the cap allows. So a robot flooding the fleet with invented outcomes moves any
figure that is a mean over pairs by at most ``max_share`` of that figure's range.

The shares are found by water-filling: the largest robots are capped one by one until every robot left under
the cap is below it. Where ``robots x max_share < 1`` no share can stay under the cap, and every robot gets an
equal share instead (1 / robots). The sample is drawn with a fixed seed, so a report repeats itself.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Collection, Sequence

import numpy as np
from numpy.typing import NDArray

SEED = 58


def robot_of(source: str) -> str:
    return source.split("/", 1)[0]


def kept_counts(counts: dict[str, int], max_share: float) -> dict[str, int]:
    """How many pairs of each robot count, so that none holds more than ``max_share`` of the total."""
    if max_share >= 1.0 or not counts:
        return dict(counts)
    if len(counts) * max_share <= 1.0:  # no share can stay under the cap: equal shares
        return dict.fromkeys(counts, min(counts.values()))
    capped: set[str] = set()
    for robot in sorted(counts, key=counts.__getitem__, reverse=True):
        free = sum(n for r, n in counts.items() if r not in capped)
        total = free / (1.0 - max_share * len(capped))  # capped robots hold max_share of it each
        if counts[robot] <= max_share * total:
            break
        capped.add(robot)
    free = sum(n for r, n in counts.items() if r not in capped)
    cap = int(max_share * free / (1.0 - max_share * len(capped)))
    return {robot: min(count, cap) if robot in capped else count for robot, count in counts.items()}


def fleet_mask(
    sources: Sequence[str], max_share: float, excluded: Collection[str] = ()
) -> tuple[NDArray[np.bool_], dict[str, float]]:
    """Which pairs count (excluded robots' pairs out, each robot's share capped) and each robot's share of them."""
    robots = np.asarray([robot_of(s) for s in sources], object)
    mask = np.zeros(len(robots), bool)
    counts = {r: n for r, n in Counter(robots.tolist()).items() if r not in excluded}
    rng = np.random.default_rng(SEED)
    for robot, keep in kept_counts(counts, max_share).items():
        rows = np.flatnonzero(robots == robot)
        mask[rows if keep >= len(rows) else np.sort(rng.choice(rows, keep, replace=False))] = True
    total = int(mask.sum())
    shares = (
        {robot: round(float((robots[mask] == robot).sum()) / total, 4) for robot in sorted(counts)} if total else {}
    )
    return mask, shares


def source_factors(
    counts: dict[str, float], max_share: float, excluded: Collection[str] = ()
) -> tuple[dict[str, float], dict[str, float]]:
    """What each source's pairs count for in summed figures (0 for an excluded robot's, else its robot's kept
    share of its pairs: kept_counts), and each robot's share of the weight, none above ``max_share``."""
    by_robot: Counter[str] = Counter()
    for source, count in counts.items():
        by_robot[robot_of(source)] += round(count)
    included = {robot: n for robot, n in by_robot.items() if robot not in excluded and n > 0}
    kept = kept_counts(included, max_share)
    factors = {
        source: kept[robot] / included[robot] if robot in included else 0.0
        for source in counts
        for robot in (robot_of(source),)
    }
    total = sum(kept.values())
    return factors, {robot: round(n / total, 4) for robot, n in sorted(kept.items())} if total else {}
