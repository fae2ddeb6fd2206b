"""What the store keeps, as plain records: experience pairs (one row per pair, columns when read back), the
anchor-set history, the active pointer and kept proposals; and the errors a store raises. No database here."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.experience import AnchorProposal
from numpy.typing import NDArray

# A pair's bytes for the max_bytes bound: 4 per weight plus stamp, outcome, sequence, kind, version index; the
# same count the msgpack store used, so a bound means what it meant (the rows on disk take more: benchmarks/store.py).
PAIR_OVERHEAD_BYTES = 8 + 8 + 8 + 1 + 2


def pair_bytes(concepts: int) -> int:
    return 4 * concepts + PAIR_OVERHEAD_BYTES


def concept_key(concepts: Sequence[str]) -> tuple[str, ...]:
    """The tuple a pair belongs to: the same concepts in another order give the same per-concept weights (the
    model scores each concept on its own; the softmax does not care about order), so the key is sorted."""
    return tuple(sorted(concepts))


# ---- errors ---------------------------------------------------------------------------------------------------


class StoreError(Exception):
    """Anything a store refuses or cannot do; the message is one line and never holds a password."""


class StoreUnavailable(StoreError):
    """The database cannot be reached or answered with a transient error: try again later, nothing is lost."""


class SchemaTooNew(StoreError):
    """The store was written by a newer gcdtrav (its schema_version is above this reader's): refused, untouched."""


# ---- experience pairs -----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PairRecord:
    """One pair to append: a cell's weights by concept (``concepts`` in concept_key order, summing to 1), the
    outcome the robot met there, and where it came from."""

    concepts: tuple[str, ...]
    weights: NDArray[np.float32]  # (n,)
    outcome: float  # in [0, 1]
    stamp: float  # the outcome's stamp, s since the epoch
    kind: int  # index into schemas.experience.OUTCOME_KINDS
    anchor_version: str  # the anchor set whose fusion made the prediction
    source: str  # the grid (robot) the outcome belongs to
    instance: str = ""  # the instance that paired it
    # Its addends of the calibration figures (experience/calibration.py pair_sums) under the grading key
    # ``graded`` (experience/graded.py), added to that key's sums in the append's transaction; None: graded
    # later, by the catch-up.
    sums: NDArray[np.float64] | None = None
    graded: str | None = None


@dataclass(frozen=True)
class SumsRow:
    """Calibration sums of one anchor-set version (the set that grades) over the pairs of one (predicting
    version, source, kind) appended in one hour (``hour`` = appended_at // 3600; ALL_HOURS: every hour)."""

    predicted: str
    source: str
    kind: int
    hour: int
    sums: NDArray[np.float64]


ALL_HOURS = -1  # the row that holds every hour's sums: the whole history, kept after the pairs go
HOURS_KEPT = 48  # hourly rows are kept this long: windows of the last hour and day


@dataclass(frozen=True)
class PairColumns:
    """One concept tuple's stored pairs, oldest first (by ``ids``, the store's append order), as columns."""

    concepts: tuple[str, ...]
    ids: NDArray[np.int64]
    weights: NDArray[np.float32]  # (m, n)
    outcomes: NDArray[np.float64]
    stamps: NDArray[np.float64]
    kinds: NDArray[np.uint8]
    versions: tuple[str, ...]
    sources: tuple[str, ...]
    appended_at: NDArray[np.float64] | None = None  # when each was appended (the writer's clock); 0: before 4
    graded: tuple[str | None, ...] = ()  # the version whose sums each was added to at append; None: none

    def __len__(self) -> int:
        return len(self.outcomes)

    @classmethod
    def empty(cls, concepts: tuple[str, ...]) -> PairColumns:
        return cls(concepts, np.zeros(0, np.int64), np.zeros((0, len(concepts)), np.float32), np.zeros(0),
                   np.zeros(0), np.zeros(0, np.uint8), (), (), np.zeros(0), ())  # fmt: skip


@dataclass(frozen=True)
class PairTotals:
    """The whole store's pairs (every tuple, every source), as the fleet-wide bounds count them."""

    pairs: int
    bytes: int


@dataclass(frozen=True)
class AppendResult:
    stored: int  # the pairs appended
    evicted: int  # the oldest pairs deleted to keep the bounds (fleet-wide)
    replayed: bool = False  # the batch's id was appended before: nothing stored again


# ---- anchor sets ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class HistoryRecord:
    """One entry of the anchor-set history: a set that became active, newest has the largest ``entry``."""

    entry: int  # the store's sequence number of this activation
    version: str  # the set's content hash (AnchorSet.version)
    anchor_set: AnchorSet
    accepted_at: float  # when it became active, s since the epoch
    how: str  # one of HOW_ACTIVATED (a plain string: a newer writer's word must not break this reader)
    forced: bool  # activated against a verdict (``--force``)
    actor: str  # who asked (an operator's name, or ''), free text
    instance: str  # the instance that wrote it


@dataclass(frozen=True)
class Activation:
    """What ``Store.activate`` did: ``applied`` False means the compare-and-swap lost and ``active`` is the
    winner (the entry that was active instead of the expected version)."""

    applied: bool
    active: HistoryRecord


@dataclass(frozen=True)
class StoredProposal:
    """A fitted proposal kept for an operator to apply by its version (``anchors propose --apply VERSION``)."""

    version: str  # the proposed set's version
    proposal: AnchorProposal
    stored_at: float
    instance: str


@dataclass(frozen=True)
class Exclusion:
    """An operator's word on one robot's pairs (its sources ``robot`` and ``robot/*``): excluded from calibration
    and fits, or included again. Every word is kept; the newest per robot is in force."""

    robot: str
    excluded: bool
    at: float  # s since the epoch
    actor: str  # who asked, free text
    reason: str
    instance: str  # the instance that wrote it


@dataclass(frozen=True)
class SourceContents:
    """What the store keeps of one source: its raw pairs, their bytes, when the oldest and newest came."""

    source: str
    pairs: int
    bytes: int
    oldest: float  # appended_at of the oldest kept pair, s since the epoch (0: appended before schema 4)
    newest: float
