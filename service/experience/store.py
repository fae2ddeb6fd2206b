"""The experience's pairs: outcomes paired with the prediction their cell had ``lookahead_s`` before, handed to
the fleet's store (service/store/, docs/calibration.md) and read back from it, the whole fleet's, for reports
and proposals. No middleware here: the bus hands it decoded payloads and asks for reports.

- **Pairs**: the cell's weights by concept, the anchor-set version that fused them, the outcome, its stamp and
  kind, the grid (robot) it belongs to. An outcome with a radius pairs every known cell within it. Pairs are
  kept per concept tuple (``concept_key``); another tuple's pairs are never mixed in.
- **Never waiting**: pairing runs on zenoh's callbacks and the worker; the pairs go to the store through the
  outbox (``PairOutbox.put`` takes one short lock). Reads (reports, proposals) run on query threads, each
  with its own connection, and hold no lock the inference path takes.
- **Bounds**: at most ``max_pairs`` pairs and ``max_bytes`` bytes in the whole store, fleet-wide, the oldest
  pair, of whatever tuple or instance, going first (the store applies them at each append).
- **Bad input**: an undecodable or invalid outcome is rejected with its reason and counted (``rejected``);
  an outcome on a cell never observed, or older than the snapshots reach, is counted and ignored.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.experience import (
    MAX_BATCH_OUTCOMES,
    OUTCOME_KINDS,
    AnchorProposal,
    CalibrationReport,
    KeptSource,
    OutcomeBatch,
    StoreContents,
    TraversalOutcome,
)
from gcdtrav.schemas.messages import MessageTooLarge
from gcdtrav.service.experience.calibration import figures_from_sums, pair_sums, ranked_figures
from gcdtrav.service.experience.fitter import FitOptions, propose
from gcdtrav.service.experience.graded import RANKED_PAIRS, GradedSums, catch_up, grading_key, set_order_weights
from gcdtrav.service.experience.pairs import Pairs
from gcdtrav.service.experience.sharing import fleet_mask, source_factors
from gcdtrav.service.experience.snapshots import SnapshotRing
from gcdtrav.service.store import (
    Exclusion,
    PairColumns,
    PairRecord,
    PairTotals,
    Store,
    StoreUnavailable,
    concept_key,
)
from gcdtrav.service.store.outbox import PairOutbox
from numpy.typing import NDArray

MAX_OUTCOME_BYTES = 4096  # an outcome is a few numbers; larger payloads are refused unread
MAX_BATCH_BYTES = 128 * MAX_BATCH_OUTCOMES  # an outcome packs to about 90 bytes in a batch
READ_OWN_WRITES_S = 2.0  # a report waits this long at most for this instance's queued pairs to be written


class OutcomeRejected(ValueError):
    def __init__(self, reason: str, detail: str) -> None:
        self.reason, self.detail = reason, detail
        super().__init__(f"{reason}: {detail}")


def as_pairs(columns: PairColumns) -> Pairs:
    arrivals = columns.appended_at if columns.appended_at is not None else np.zeros(len(columns))  # append order
    return Pairs(
        columns.concepts, columns.weights, columns.outcomes, columns.stamps, columns.kinds, columns.versions, arrivals
    )


class ExperienceStore:
    """Thread-safe: outcomes arrive from zenoh callbacks, reports and fits from queries."""

    def __init__(
        self,
        outbox: PairOutbox,
        source: str,
        lookahead_s: float,
        instance: str = "",
        clock: Callable[[], float] = time.time,
        max_robot_share: float = 1.0,
        tau: float | None = None,
    ) -> None:
        """``source``: the grid the pairs belong to (a robot's); ``instance``: who paired them;
        ``max_robot_share``: the most of the graded or fitted pairs one robot may hold (sharing.py); ``tau``:
        pairs are graded as they are made, under the set that predicted them, for the reports' sums (graded.py);
        None: graded at the first report (the catch-up)."""
        self.outbox, self.source, self.lookahead_s, self.instance, self.clock = (
            outbox, source, lookahead_s, instance, clock
        )  # fmt: skip
        self.max_robot_share, self.tau = max_robot_share, tau
        self.counts: dict[str, int] = {}
        self._lock = threading.Lock()  # the counters only: never held across a store call

    # ---- counters --------------------------------------------------------------------------------------
    def _count(self, name: str, by: int = 1) -> None:
        self.counts[name] = self.counts.get(name, 0) + by

    def totals(self) -> PairTotals:
        """Pairs and bytes in the whole store (every instance's), as the outbox's writer last read them: a
        status never waits on the store."""
        return self.outbox.totals

    # ---- outcomes in -----------------------------------------------------------------------------------
    def ingest(self, payload: bytes, ring: SnapshotRing) -> int:
        """Decode an outcome payload (msgpack or JSON) and pair it; OutcomeRejected (counted) for a bad one."""
        with self._rejections():
            outcome = TraversalOutcome.decode(payload, MAX_OUTCOME_BYTES)
        return self.add(outcome, ring)

    def ingest_batch(self, payload: bytes, ring: SnapshotRing) -> tuple[int, int]:
        """Decode a relay's batch and pair each of its outcomes as one from the bus: (pairs made, outcomes left
        out); OutcomeRejected (counted) for a bad batch. An outcome of it this service does not take is left out
        and counted (``rejected_bad_outcome``), the others paired; the outcomes the relay dropped are counted
        (``relay_dropped``)."""
        with self._rejections():
            batch, left_out = OutcomeBatch.decode_each(payload, MAX_BATCH_BYTES)
        with self._lock:
            self._count("relayed_outcomes", len(batch.outcomes))
            if left_out:
                self._count("rejected_bad_outcome", left_out)
            if batch.dropped:
                self._count("relay_dropped", batch.dropped)
        return sum(self.add(outcome, ring) for outcome in batch.outcomes), left_out

    @contextmanager
    def _rejections(self) -> Iterator[None]:
        """A payload decoded: too large, or not valid, is an OutcomeRejected counted by its reason."""
        try:
            yield
        except MessageTooLarge as err:
            raise self._rejected("oversized", str(err)) from None
        except ValueError as err:  # MessageError, or whatever else a bad value raised
            raise self._rejected("bad_outcome", str(err)) from None

    def _rejected(self, reason: str, detail: str) -> OutcomeRejected:
        with self._lock:
            self._count(f"rejected_{reason}")
        return OutcomeRejected(reason, detail)

    def add(self, outcome: TraversalOutcome, ring: SnapshotRing) -> int:
        """Pair the outcome with every known cell in its footprint as ``ring`` held it ``lookahead_s`` before;
        the number of pairs made (0: counted as ignored, with the reason)."""
        snapshot = ring.before(outcome.stamp - self.lookahead_s)
        if snapshot is None:
            with self._lock:
                self._count("outcomes")
                self._count("ignored_no_prediction")
            return 0
        _, weights = snapshot.weights_at(snapshot.cells_near(outcome.x, outcome.y, outcome.radius_m))
        return self.add_predicted(weights, snapshot.anchors, outcome)

    def add_predicted(self, weights: np.ndarray, anchors: AnchorSet, outcome: TraversalOutcome) -> int:
        """Pair the outcome with given predictions: (cells, n) weights over ``anchors`` (an operator's answer
        pairs with the cells its question showed). The pairs go to the outbox: never a wait on the store."""
        if len(weights) == 0:
            with self._lock:
                self._count("outcomes")
                self._count("ignored_unknown_cell")
            return 0
        key = concept_key(anchors.concepts)
        column = [anchors.concepts.index(c) for c in key]
        kind = OUTCOME_KINDS.index(outcome.kind)
        cells = np.asarray(weights, np.float64)
        cells = cells[cells.sum(axis=1) > 0]
        stored = (cells / cells.sum(axis=1, keepdims=True)).astype(np.float32)  # graded as the store keeps them
        graded = None if self.tau is None else grading_key(anchors, self.tau)
        sums = None if self.tau is None else pair_sums(stored, np.full(len(stored), outcome.score), anchors, self.tau)
        records = [
            PairRecord(key, stored[i, column], outcome.score, outcome.stamp, kind, anchors.version, self.source,
                       self.instance, None if sums is None else sums[i], graded)
            for i in range(len(stored))
        ]  # fmt: skip
        accepted = self.outbox.put(records) if records else 0
        with self._lock:
            self._count("outcomes")
            self._count("pairs", accepted)
            if accepted < len(records):
                self._count("dropped_store_outbox_full", len(records) - accepted)
        return accepted

    # ---- reading: the fleet's pairs ------------------------------------------------------------------------
    def tuples(self) -> list[tuple[str, ...]]:
        """The concept tuples with pairs in the store (this instance's queued ones written first)."""
        self.outbox.flush(READ_OWN_WRITES_S)
        return self._store().tuples()

    def columns(self, concepts: Sequence[str], source: str | None = None) -> PairColumns:
        """The fleet's pairs of this concept tuple (any order of the same concepts), oldest first; this
        instance's queued pairs are written first (for up to READ_OWN_WRITES_S). StoreUnavailable if the store
        cannot be read."""
        self.outbox.flush(READ_OWN_WRITES_S)
        return self._store().pairs(concepts, source)

    def pairs(self, concepts: Sequence[str], source: str | None = None) -> Pairs:
        return as_pairs(self.columns(concepts, source))

    def fleet_columns(self, concepts: Sequence[str], sample: bool = False) -> FleetPairs:
        """The fleet's pairs of this tuple that count: excluded robots' out, each robot's share capped. With
        ``sample``: each source's fitting sample (its whole history), or its retained pairs where the sample
        holds fewer (a source whose pairs came before the sample existed)."""
        columns = self.columns(concepts)
        if sample:
            columns = sampled_history(columns, self._store().sample(concepts), self.outbox.sample_size)
        excluded = excluded_robots(self._store())
        mask, shares = fleet_mask(columns.sources, self.max_robot_share, excluded)
        return FleetPairs(as_pairs(columns).select(mask), shares, excluded)

    # ---- exclusions ------------------------------------------------------------------------------------
    def exclude(self, robot: str, excluded: bool, actor: str = "", reason: str = "") -> list[Exclusion]:
        """Record an operator's exclusion of ``robot``'s pairs (or its inclusion again); the words in force."""
        store = self._store()
        store.exclude(Exclusion(robot, excluded, round(self.clock(), 3), actor, reason, self.instance))
        return store.exclusions()

    def exclusions(self) -> list[Exclusion]:
        return self._store().exclusions()

    def contents(self) -> StoreContents:
        """What the fleet's store keeps: each source's raw pairs (a scan), the calibration sums."""
        store = self._store()
        totals, age = store.totals(), self.outbox.max_age_s
        return StoreContents(
            backend=self.outbox.backend,
            location=self.outbox.location,
            pairs=totals.pairs,
            bytes=totals.bytes,
            max_pairs=self.outbox.max_pairs,
            max_bytes=self.outbox.max_bytes,
            max_age_days=None if age is None else age / 86_400.0,
            sources=[KeptSource(**vars(kept)) for kept in store.contents()],
            graded=store.graded_keys(),
        )

    def _store(self) -> Store:
        store = self.outbox.store
        if store is None:
            state = self.outbox.state()
            raise StoreUnavailable(f"the store {state.location} has been unreachable since this start: {state.error}")
        return store

    def report(self, anchors: AnchorSet, tau: float, by_source: bool = False, window: str = "all") -> CalibrationReport:
        """The active set graded by the fleet's pairs of its tuple (every source's, each robot's share capped,
        excluded robots' out), from the sums the store keeps (graded.py): the catch-up first adds the pairs
        the set has not graded yet. ``window``: all, hour or day (by the hour the pairs were appended);
        ``by_source``: each source's figures too."""
        self.outbox.flush(READ_OWN_WRITES_S)
        store, now = self._store(), self.clock()
        catch_up(store, anchors, tau)
        excluded = excluded_robots(store)
        graded = GradedSums.read(store, grading_key(anchors, tau), len(anchors), window, store.clock(), excluded)
        counts = {source: float(sums[0]) for source, sums in graded.by_source.items()}
        factors, shares = source_factors(counts, self.max_robot_share, excluded)
        # AUSE and Spearman: the newest pairs in the window, excluded robots out, each robot's share capped
        newest = store.pairs(anchors.concepts, limit=RANKED_PAIRS, newest_first=True)
        newest_weights, newest_sources = set_order_weights(newest, anchors), np.asarray(newest.sources, object)
        in_window = newest.appended_at >= graded.since if newest.appended_at is not None else np.ones(len(newest))
        counted, _ = fleet_mask(newest.sources, self.max_robot_share, excluded)
        counted &= np.asarray(in_window, bool)

        def ranked(chosen: NDArray[np.bool_]) -> tuple[float | None, float | None]:
            return ranked_figures(newest_weights[chosen], newest.outcomes[chosen], anchors)

        figures = figures_from_sums(graded.total(factors), anchors, tau, *ranked(counted))
        breakdown = None
        if by_source:
            breakdown = {
                source: figures_from_sums(sums, anchors, tau, *ranked((newest_sources == source) & in_window))
                for source, sums in sorted(graded.by_source.items())
            }
        totals = self.totals()
        with self._lock:
            kept = {**self.counts, "stored_pairs": totals.pairs, "stored_bytes": totals.bytes}
        return CalibrationReport(
            source=self.source,
            stamp=now,
            anchor_set_version=anchors.version,
            concepts=anchors.concepts,
            figures=figures,
            pairs_by_kind=graded.by_kind,
            pairs_by_version=graded.by_version,
            counts=kept,
            pairs_by_source={s: round(c) for s, c in sorted(counts.items())},
            by_source=breakdown,
            share_by_robot=shares,
            excluded_robots=excluded,
        )

    def propose(
        self, source: str, anchors: AnchorSet, options: FitOptions, baselines: Sequence[tuple[str, AnchorSet]] = ()
    ) -> AnchorProposal:
        """An AnchorProposal fitted on the fitting sample of this tuple (each source's whole history), judged on
        the latest of it, also against ``baselines`` (ValueError without pairs)."""
        fleet = self.fleet_columns(anchors.concepts, sample=True)
        proposal = propose(fleet.pairs, anchors, options, source, self.clock(), baselines)
        return proposal.model_copy(update={"share_by_robot": fleet.shares, "excluded_robots": fleet.excluded})


@dataclass(frozen=True)
class FleetPairs:
    """The pairs that count for the fleet (sharing.py), each robot's share, the excluded robots."""

    pairs: Pairs
    shares: dict[str, float]
    excluded: list[str]


def excluded_robots(store: Store) -> list[str]:
    """The robots an operator's word in force leaves out."""
    return [word.robot for word in store.exclusions() if word.excluded]


def sampled_history(retained: PairColumns, sample: PairColumns, size: int) -> PairColumns:
    """Per source, its fitting sample where that is full (``size``) or holds at least its retained pairs, else its
    retained pairs: after an upgrade, a source's older pairs are not in the sample yet."""
    retained_count, sampled_count = Counter(retained.sources), Counter(sample.sources)
    from_sample = {
        s for s in retained_count | sampled_count if sampled_count[s] >= min(retained_count[s], size or 1 << 62)
    }
    keep_sample = np.asarray([s in from_sample for s in sample.sources], bool)
    keep_retained = np.asarray([s not in from_sample for s in retained.sources], bool)

    def joined(column: str) -> Any:  # the sample's rows kept, then the retained ones
        first, second = getattr(sample, column), getattr(retained, column)
        if isinstance(first, tuple):  # versions and sources
            return tuple(np.asarray(first, object)[keep_sample]) + tuple(np.asarray(second, object)[keep_retained])
        return np.concatenate([first[keep_sample], second[keep_retained]])

    columns = ("ids", "weights", "outcomes", "stamps", "kinds", "versions", "sources")
    return PairColumns(retained.concepts, **{column: joined(column) for column in columns})
