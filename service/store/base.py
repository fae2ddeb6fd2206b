"""The one interface of what the fleet must remember (issue 46): experience pairs, the anchor-set history, the
active set, kept proposals. Two backends implement it with one schema (``schema.py``): SQLite in the state dir
(the default, nothing to set up) and PostgreSQL (a fleet's shared database). No middleware, no experience logic.

Every method is thread-safe and may block on the database: callers on the inference path never call it
directly (pairs go through ``outbox.PairOutbox``). A connection problem raises ``StoreUnavailable`` (retry
later); a store of a newer schema raises ``SchemaTooNew`` at opening.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence

from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.experience import AnchorProposal
from gcdtrav.service.store.records import (
    Activation,
    AppendResult,
    Exclusion,
    HistoryRecord,
    PairColumns,
    PairRecord,
    PairTotals,
    SourceContents,
    StoredProposal,
    SumsRow,
)


class Store(ABC):
    backend: str  # "sqlite" or "postgresql"
    clock: Callable[[], float] = staticmethod(time.time)  # when pairs are appended: the windows' clock

    @property
    @abstractmethod
    def location(self) -> str:
        """Where it is, for logs and status: a file path, or a URL without any password."""

    # ---- experience pairs ------------------------------------------------------------------------------
    @abstractmethod
    def append_pairs(
        self,
        pairs: Sequence[PairRecord],
        max_pairs: int,
        max_bytes: int,
        batch_id: str | None = None,
        max_age_s: float | None = None,
        sample_size: int = 0,
    ) -> AppendResult:
        """Append in one transaction (inserts only), then delete the oldest pairs of the whole store, any tuple
        and source, until at most ``max_pairs`` pairs and ``max_bytes`` bytes (records.pair_bytes) remain, and
        those appended more than ``max_age_s`` ago (calibration's sums stay). With ``sample_size``, each pair
        may also enter its (tuple, source)'s fitting sample (``sample``). A
        ``batch_id`` the store already holds (the batch was committed, its answer lost, and it comes again)
        stores nothing: ``AppendResult(0, 0, replayed=True)``."""

    @abstractmethod
    def pairs(
        self,
        concepts: Sequence[str],
        source: str | None = None,
        after_id: int = 0,
        limit: int | None = None,
        newest_first: bool = False,
    ) -> PairColumns:
        """The pairs of this concept tuple (concepts in any order; columns in concept_key order), oldest first;
        only ``source``'s when given, only those after ``after_id``; ``limit`` of them, the newest with
        ``newest_first`` (still returned oldest first)."""

    # ---- calibration sums ------------------------------------------------------------------------------
    @abstractmethod
    def add_sums(self, graded: str, rows: Sequence[SumsRow], from_id: int, upto_id: int) -> bool:
        """Add calibration sums under the grading key ``graded`` (each row to its hour and to all hours) and
        move its watermark from ``from_id`` to ``upto_id`` (the catch-up), in one transaction; False, with
        nothing added, when the watermark is no longer ``from_id`` (another instance added them)."""

    @abstractmethod
    def sums(self, graded: str, since_hour: int | None = None) -> list[SumsRow]:
        """The sums graded by ``graded``: of all hours (None), or the hourly rows since ``since_hour``."""

    @abstractmethod
    def contents(self) -> list[SourceContents]:
        """What is kept of each source's raw pairs (a scan of the pairs: an operator's question, not a report's)."""

    @abstractmethod
    def graded_keys(self) -> dict[str, int]:
        """The calibration sums kept: pairs graded per grading key (``version@tau``)."""

    @abstractmethod
    def graded_upto(self, graded: str) -> int:
        """The last pair id the catch-up has added to ``graded``'s sums (0: none yet)."""

    @abstractmethod
    def sample(self, concepts: Sequence[str]) -> PairColumns:
        """The fitting sample of this tuple: per source a uniform sample of its whole history (kept after the raw
        pairs go), by stamp; ``ids`` are slots, not pair ids."""

    @abstractmethod
    def tuples(self) -> list[tuple[str, ...]]:
        """The concept tuples that have pairs, sorted."""

    @abstractmethod
    def totals(self) -> PairTotals:
        """Pairs and bytes in the whole store."""

    # ---- anchor sets -----------------------------------------------------------------------------------
    @abstractmethod
    def active(self) -> HistoryRecord | None:
        """The active set's history entry; None in an empty store (before ``seed``)."""

    @abstractmethod
    def seed(self, anchors: AnchorSet, instance: str, how: str = "seeded", accepted_at: float = 0.0) -> HistoryRecord:
        """Make ``anchors`` active only if no set is (an empty store): the start set seeds, never overrides.
        The active entry afterwards, whichever it is."""

    @abstractmethod
    def activate(
        self,
        anchors: AnchorSet,
        expected_active_version: str | None,
        how: str,
        instance: str,
        actor: str = "",
        forced: bool = False,
        accepted_at: float | None = None,
    ) -> Activation:
        """One transaction: if the active set's version is ``expected_active_version`` (None: whatever it is),
        append ``anchors`` to the history and point the active pointer at it (``applied``); else change
        nothing and return the winner. ``accepted_at`` None: now."""

    @abstractmethod
    def history(self, limit: int = 20) -> list[HistoryRecord]:
        """The last ``limit`` activations, newest (the active one, unless a swap is under way) first."""

    @abstractmethod
    def put_proposal(self, proposal: AnchorProposal, instance: str) -> StoredProposal:
        """Keep a proposal under its proposed version (a later one of the same version replaces it)."""

    @abstractmethod
    def proposal(self, version: str) -> StoredProposal | None:
        """The kept proposal of that proposed version; None if there is none (or it was pruned)."""

    # ---- exclusions ------------------------------------------------------------------------------------
    @abstractmethod
    def exclude(self, exclusion: Exclusion) -> None:
        """Record an operator's exclusion (or inclusion again) of a robot's pairs."""

    @abstractmethod
    def exclusions(self) -> list[Exclusion]:
        """The word in force per robot (its newest), excluded or included again, by robot."""

    # ---- lifetime --------------------------------------------------------------------------------------
    @abstractmethod
    def close(self) -> None:
        """Close every connection; the store is unusable afterwards."""
