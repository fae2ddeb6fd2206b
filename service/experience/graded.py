"""Calibration from sums kept as pairs arrive (issue 57, docs/calibration.md "At fleet scale"): grading costs
the same at 10^4 and 10^8 pairs.

Every figure but AUSE and Spearman's rho is a sum over pairs (calibration.pair_sums). The store keeps those
sums per *grading key* (the anchor-set version that grades, and tau: ``version@tau``), per predicting version,
source, kind and hour of appending, and for all hours; they outlive the pairs, which the store's bounds evict.

- A pair is added to its own set's sums in the append's transaction (the experience grades it as it pairs).
- A set that grades pairs it did not predict (the active set after a swap grades the tuple's older pairs, or
  pairs another instance still on the old set makes) has them added by the **catch-up**: before a report, the
  pairs after the key's watermark that were not graded under the key at append are graded and added, with
  the watermark, in one transaction. After a swap this reads each retained pair once (chunks of
  CATCH_UP_CHUNK), then only what came since. Pairs evicted before a set ever graded them are not in its sums.
- AUSE and Spearman's rho rank all pairs, so no sum keeps them: they come from the newest RANKED_PAIRS pairs.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Collection
from dataclasses import dataclass, field

import numpy as np
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.experience import OUTCOME_KINDS
from gcdtrav.service.experience.calibration import pair_sums, sums_length
from gcdtrav.service.experience.sharing import robot_of
from gcdtrav.service.store import PairColumns, Store, SumsRow
from numpy.typing import NDArray

RANKED_PAIRS = 10_000  # AUSE and Spearman's rho: over the newest pairs of the tuple (half the cost of a report)
CATCH_UP_CHUNK = 50_000  # pairs read and graded per transaction by the catch-up
WINDOW_HOURS = {"all": None, "hour": 1, "day": 24}  # a report's windows, by the hour the pairs were appended


def grading_key(anchors: AnchorSet, tau: float) -> str:
    """Whose sums: the set that grades, and tau (P(T < tau) is in the sums; another tau is another key)."""
    return f"{anchors.version}@{tau:g}"


def set_order_weights(columns: PairColumns, anchors: AnchorSet) -> NDArray[np.float64]:
    """The stored weights (concept_key order) in the set's concept order."""
    order = [columns.concepts.index(c) for c in anchors.concepts]
    return np.asarray(columns.weights, np.float64)[:, order]


def grouped(sums: NDArray[np.float64], predicted: list[str], sources: list[str], kinds: list[int],
            hours: list[int]) -> list[SumsRow]:  # fmt: skip
    """Pairs' sums added up per (predicting version, source, kind, hour)."""
    totals: dict[tuple[str, str, int, int], NDArray[np.float64]] = {}
    for row, key in enumerate(zip(predicted, sources, kinds, hours, strict=True)):
        totals[key] = totals[key] + sums[row] if key in totals else sums[row].copy()
    return [SumsRow(v, s, k, h, total) for (v, s, k, h), total in totals.items()]


def catch_up(store: Store, anchors: AnchorSet, tau: float) -> int:
    """Add to the key's sums every retained pair of the set's tuple it does not hold yet; how many."""
    key, added = grading_key(anchors, tau), 0
    while True:
        upto = store.graded_upto(key)
        chunk = store.pairs(anchors.concepts, after_id=upto, limit=CATCH_UP_CHUNK)
        if len(chunk) == 0:
            return added
        todo = np.flatnonzero(np.asarray([graded != key for graded in chunk.graded], bool))
        rows: list[SumsRow] = []
        if len(todo):
            sums = pair_sums(set_order_weights(chunk, anchors)[todo], chunk.outcomes[todo], anchors, tau)
            appended = chunk.appended_at if chunk.appended_at is not None else np.zeros(len(chunk))
            hours = [int(h) for h in appended[todo] // 3600]  # the store keeps recent hours, all in all hours
            rows = grouped(sums, [chunk.versions[i] for i in todo], [chunk.sources[i] for i in todo],
                           [int(chunk.kinds[i]) for i in todo], hours)  # fmt: skip
        if store.add_sums(key, rows, from_id=upto, upto_id=int(chunk.ids[-1])):
            added += len(todo)


@dataclass
class GradedSums:
    """A key's sums over one window, added up per source, and the pair counts by kind and predicting version."""

    length: int
    since: float = 0.0  # the window's start, s since the epoch (0: all)
    by_source: dict[str, NDArray[np.float64]] = field(default_factory=dict)
    by_kind: dict[str, int] = field(default_factory=dict)
    by_version: dict[str, int] = field(default_factory=dict)

    @classmethod
    def read(
        cls, store: Store, key: str, concepts: int, window: str, now: float, excluded: Collection[str] = ()
    ) -> GradedSums:
        """The sums of ``window``, excluded robots' left out."""
        hours = WINDOW_HOURS[window]
        since_hour = None if hours is None else int(now // 3600) - hours
        rows = store.sums(key, since_hour)
        graded = cls(sums_length(concepts), 0.0 if since_hour is None else 3600.0 * since_hour)
        by_kind: dict[str, int] = defaultdict(int)
        by_version: dict[str, int] = defaultdict(int)
        for row in rows:
            if robot_of(row.source) in excluded:
                continue
            if row.source in graded.by_source:
                graded.by_source[row.source] = graded.by_source[row.source] + row.sums
            else:
                graded.by_source[row.source] = row.sums.copy()
            by_kind[OUTCOME_KINDS[row.kind]] += round(float(row.sums[0]))
            by_version[row.predicted] += round(float(row.sums[0]))
        graded.by_kind, graded.by_version = dict(sorted(by_kind.items())), dict(sorted(by_version.items()))
        return graded

    def total(self, factors: dict[str, float]) -> NDArray[np.float64]:
        """The sources' sums, each times its factor (a robot's share capped, or 0 when excluded)."""
        total = np.zeros(self.length)
        for source, sums in self.by_source.items():
            total += factors.get(source, 1.0) * sums
        return total
