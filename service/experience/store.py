"""The experience store: outcomes paired with the prediction their cell had ``lookahead_s`` before, bounded and
persisted (docs/calibration.md). No middleware here: the bus hands it decoded payloads and asks for reports.

- **Pairs**: the cell's weights by concept, the anchor-set version that fused them, the outcome, its stamp and
  kind. An outcome with a radius pairs every known cell within it. Pairs are kept per concept tuple
  (``pairs.concept_key``); another tuple's pairs are never mixed in.
- **Bounds**: at most ``max_pairs`` pairs and ``max_bytes`` bytes (each pair costs 4 bytes per anchor plus
  ``PAIR_OVERHEAD_BYTES``), the oldest pair, of whatever tuple, going first.
- **Bad input**: an undecodable or invalid outcome is rejected with its reason and counted (``rejected``);
  an outcome on a cell never observed, or older than the snapshots reach, is counted and ignored.
- **On disk**: one msgpack file in the state dir, written like the anchor state (temporary file, fsync,
  rename, fsync the folder): a crash leaves the last whole file. A failed write (full disk, read-only dir)
  is one log line and a count; the pairs stay in memory and the last good file on disk.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.experience import OUTCOME_KINDS, AnchorProposal, CalibrationReport, TraversalOutcome
from gcdtrav.schemas.messages import MessageTooLarge
from gcdtrav.service.experience.calibration import calibration_figures
from gcdtrav.service.experience.fitter import FitOptions, propose
from gcdtrav.service.experience.pairs import Pairs, concept_key
from gcdtrav.service.experience.snapshots import SnapshotRing
from gcdtrav.service.runtime.fleet.state import remove_stale_temporaries, write_atomically

log = logging.getLogger("gcdtrav.service")

FILE_FORMAT = 1
PAIR_OVERHEAD_BYTES = 8 + 8 + 8 + 1 + 2  # stamp, outcome, sequence, kind, version index
MAX_OUTCOME_BYTES = 4096  # an outcome is a few numbers; larger payloads are refused unread


class OutcomeRejected(ValueError):
    def __init__(self, reason: str, detail: str) -> None:
        self.reason, self.detail = reason, detail
        super().__init__(f"{reason}: {detail}")


def decode_outcome(payload: bytes) -> TraversalOutcome:
    """A TraversalOutcome from msgpack or JSON (a payload starting with '{'); OutcomeRejected with the reason."""
    try:
        return TraversalOutcome.decode(payload, MAX_OUTCOME_BYTES)
    except MessageTooLarge as err:
        raise OutcomeRejected("oversized", str(err)) from None
    except ValueError as err:  # MessageError, or whatever else a bad value raised
        raise OutcomeRejected("bad_outcome", str(err)) from None


@dataclass
class _Bucket:
    concepts: tuple[str, ...]
    weights: deque[np.ndarray] = field(default_factory=deque)
    outcomes: deque[float] = field(default_factory=deque)
    stamps: deque[float] = field(default_factory=deque)
    kinds: deque[int] = field(default_factory=deque)
    versions: deque[str] = field(default_factory=deque)
    sequence: deque[int] = field(default_factory=deque)

    @property
    def pair_bytes(self) -> int:
        return 4 * len(self.concepts) + PAIR_OVERHEAD_BYTES

    def append(self, weights: np.ndarray, outcome: float, stamp: float, kind: int, version: str, seq: int) -> None:
        self.weights.append(weights.astype(np.float32))
        self.outcomes.append(outcome)
        self.stamps.append(stamp)
        self.kinds.append(kind)
        self.versions.append(version)
        self.sequence.append(seq)

    def pop_oldest(self) -> None:
        for column in (self.weights, self.outcomes, self.stamps, self.kinds, self.versions, self.sequence):
            column.popleft()

    def pairs(self) -> Pairs:
        n = len(self.concepts)
        weights = np.stack(list(self.weights)) if self.weights else np.zeros((0, n), np.float32)
        return Pairs(
            self.concepts,
            weights.astype(np.float32),
            np.asarray(self.outcomes, np.float64),
            np.asarray(self.stamps, np.float64),
            np.asarray(self.kinds, np.uint8),
            tuple(self.versions),
        )


class ExperienceStore:
    """Thread-safe: outcomes arrive from zenoh callbacks, reports and fits from queries."""

    def __init__(
        self,
        path: Path | None,
        max_pairs: int,
        max_bytes: int,
        lookahead_s: float,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.path, self.max_pairs, self.max_bytes, self.lookahead_s = path, max_pairs, max_bytes, lookahead_s
        self.clock = clock
        self._buckets: dict[tuple[str, ...], _Bucket] = {}
        self._order: deque[tuple[str, ...]] = deque()  # the bucket of every pair, oldest first
        self._bytes = 0
        self._seq = 0
        self._dirty = False
        self._save_error: str | None = None
        self.counts: dict[str, int] = {}
        self._lock = threading.Lock()
        if path is not None:
            self._load(path)

    # ---- counters --------------------------------------------------------------------------------------
    def _count(self, name: str, by: int = 1) -> None:
        self.counts[name] = self.counts.get(name, 0) + by

    @property
    def size(self) -> int:
        return len(self._order)

    @property
    def nbytes(self) -> int:
        return self._bytes

    # ---- outcomes in -----------------------------------------------------------------------------------
    def ingest(self, payload: bytes, ring: SnapshotRing) -> int:
        """Decode an outcome payload and pair it; OutcomeRejected (counted) for a bad one."""
        try:
            outcome = decode_outcome(payload)
        except OutcomeRejected as err:
            with self._lock:
                self._count(f"rejected_{err.reason}")
            raise
        return self.add(outcome, ring)

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
        pairs with the cells its question showed)."""
        with self._lock:
            self._count("outcomes")
            if len(weights) == 0:
                self._count("ignored_unknown_cell")
                return 0
            key = concept_key(anchors.concepts)
            bucket = self._buckets.setdefault(key, _Bucket(key))
            column = [anchors.concepts.index(c) for c in key]
            kind = OUTCOME_KINDS.index(outcome.kind)
            made = 0
            for row in np.asarray(weights, np.float32)[:, column]:
                total = float(row.sum())
                if not total > 0:
                    continue
                bucket.append(row / total, outcome.score, outcome.stamp, kind, anchors.version, self._seq)
                self._seq += 1
                self._order.append(key)
                self._bytes += bucket.pair_bytes
                made += 1
            if not bucket.outcomes:
                del self._buckets[key]
            self._count("pairs", made)
            self._evict()
            self._dirty = True
            return made

    def _evict(self) -> None:
        while self._order and (len(self._order) > self.max_pairs or self._bytes > self.max_bytes):
            bucket = self._buckets[self._order.popleft()]
            bucket.pop_oldest()
            self._bytes -= bucket.pair_bytes
            self._count("evicted")
            if not bucket.outcomes:
                del self._buckets[bucket.concepts]

    # ---- reading ---------------------------------------------------------------------------------------
    def tuples(self) -> list[tuple[str, ...]]:
        with self._lock:
            return sorted(self._buckets)

    def pairs(self, concepts: list[str] | tuple[str, ...]) -> Pairs:
        """The pairs of this concept tuple (any order of the same concepts), oldest first."""
        key = concept_key(concepts)
        with self._lock:
            bucket = self._buckets.get(key)
            return bucket.pairs() if bucket is not None else Pairs.empty(key)

    def report(self, source: str, anchors: AnchorSet, tau: float) -> CalibrationReport:
        pairs = self.pairs(anchors.concepts)
        figures = calibration_figures(pairs.weights_for(anchors), pairs.outcomes, anchors, tau)
        with self._lock:
            counts = {**self.counts, "stored_pairs": len(self._order), "stored_bytes": self._bytes}
        return CalibrationReport(
            source=source,
            stamp=self.clock(),
            anchor_set_version=anchors.version,
            concepts=anchors.concepts,
            figures=figures,
            pairs_by_kind=pairs.count_by_kind(),
            pairs_by_version=pairs.count_by_version(),
            counts=counts,
        )

    def propose(
        self, source: str, anchors: AnchorSet, options: FitOptions, baselines: Sequence[tuple[str, AnchorSet]] = ()
    ) -> AnchorProposal:
        """An AnchorProposal fitted on this tuple's pairs, judged also against ``baselines`` (ValueError without
        pairs)."""
        return propose(self.pairs(anchors.concepts), anchors, options, source, self.clock(), baselines)

    # ---- persistence -----------------------------------------------------------------------------------
    def save(self) -> bool:
        """Write the pairs atomically; False (logged once, counted) if the state dir refuses."""
        if self.path is None:
            return False
        with self._lock:
            payload = self._serialised()
            self._dirty = False
        try:
            write_atomically(self.path, payload)
        except OSError as err:
            with self._lock:
                self._count("save_failed")
                self._dirty = True
                message = str(err.strerror or err)
                first = self._save_error != message
                self._save_error = message
            if first:
                log.error("cannot write the experience store %s: %s; pairs kept in memory", self.path, message)
            return False
        if self._save_error is not None:
            log.info("experience store %s written again", self.path)
            self._save_error = None
        return True

    def save_if_dirty(self) -> bool:
        return self.save() if self._dirty else False

    def _serialised(self) -> bytes:
        buckets = []
        for bucket in self._buckets.values():
            pairs = bucket.pairs()
            versions = sorted(set(pairs.versions))
            index = {v: i for i, v in enumerate(versions)}
            buckets.append(
                {
                    "concepts": list(bucket.concepts),
                    "versions": versions,
                    "weights": pairs.weights.astype("<f4").tobytes(),
                    "outcomes": pairs.outcomes.astype("<f8").tobytes(),
                    "stamps": pairs.stamps.astype("<f8").tobytes(),
                    "kinds": pairs.kinds.astype("u1").tobytes(),
                    "version_index": np.asarray([index[v] for v in pairs.versions], "<u2").tobytes(),
                    "sequence": np.asarray(bucket.sequence, "<i8").tobytes(),
                }
            )
        document = {"format": FILE_FORMAT, "buckets": buckets, "counts": self.counts}
        return bytes(msgpack.packb(document, use_bin_type=True))

    def _load(self, path: Path) -> None:
        try:
            if path.parent.is_dir():
                remove_stale_temporaries(path)
            if not path.is_file():
                return
            document = msgpack.unpackb(path.read_bytes(), raw=False)
            self._restore(document)
        except (OSError, ValueError, KeyError, TypeError, msgpack.UnpackException) as err:
            self._buckets, self._order, self._bytes = {}, deque(), 0
            self._count("load_failed")
            log.error("ignoring the experience store %s: %s; starting without pairs", path, err)

    def _restore(self, document: dict[str, Any]) -> None:
        if document.get("format") != FILE_FORMAT:
            raise ValueError(f"format {document.get('format')!r}, this reader reads {FILE_FORMAT}")
        entries: list[tuple[int, tuple[str, ...]]] = []
        for item in document["buckets"]:
            key = tuple(str(c) for c in item["concepts"])
            n = len(key)
            weights = np.frombuffer(item["weights"], "<f4").reshape(-1, n)
            outcomes = np.frombuffer(item["outcomes"], "<f8")
            stamps = np.frombuffer(item["stamps"], "<f8")
            kinds = np.frombuffer(item["kinds"], "u1")
            version_index = np.frombuffer(item["version_index"], "<u2")
            sequence = np.frombuffer(item["sequence"], "<i8")
            if not len(weights) == len(outcomes) == len(stamps) == len(kinds) == len(version_index) == len(sequence):
                raise ValueError(f"the columns of {list(key)} differ in length")
            bucket = _Bucket(key)
            for k in range(len(outcomes)):
                bucket.append(weights[k], float(outcomes[k]), float(stamps[k]), int(kinds[k]),
                              str(item["versions"][version_index[k]]), int(sequence[k]))  # fmt: skip
            self._buckets[key] = bucket
            entries += [(int(s), key) for s in sequence]
            self._bytes += bucket.pair_bytes * len(outcomes)
        entries.sort()
        self._order = deque(key for _, key in entries)
        self._seq = entries[-1][0] + 1 if entries else 0
        self.counts = {str(k): int(v) for k, v in document.get("counts", {}).items()}
        self._evict()  # smaller caps than the file was written with
