"""The store's logic in SQL, once, for both backends (``schema.Dialect`` fills in the differences); a backend
gives only connections and transactions (``_transaction``), and maps its driver's errors.

Writers are serialised per table group: a backend's write transaction takes the group's lock first (SQLite:
its one writer lock; PostgreSQL: a transaction-scoped advisory lock), so the fleet-wide totals and the
active pointer are read and changed by one writer at a time and a compare-and-swap cannot interleave."""

from __future__ import annotations

import json
import random
import time
from abc import abstractmethod
from collections.abc import Sequence
from contextlib import AbstractContextManager
from typing import Any, Literal, Protocol

import numpy as np
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.experience import AnchorProposal
from gcdtrav.service.store.base import Store
from gcdtrav.service.store.records import (
    ALL_HOURS,
    HOURS_KEPT,
    Activation,
    AppendResult,
    Exclusion,
    HistoryRecord,
    PairColumns,
    PairRecord,
    PairTotals,
    SchemaTooNew,
    SourceContents,
    StoredProposal,
    SumsRow,
    concept_key,
    pair_bytes,
)
from gcdtrav.service.store.schema import MIGRATIONS, SCHEMA_VERSION, VERSION_TABLE, Dialect
from numpy.typing import NDArray

Lock = Literal["schema", "pairs", "anchors"]
BATCH_IDS_KEPT_S = 86_400.0  # a batch's id is remembered a day: its replays come within the outbox's retries
EVICT_CHUNK = 10_000  # oldest rows looked at per step while finding where the bounds are kept
_RANDOM = random.Random()  # the fitting sample's reservoir draws


class Cursor(Protocol):
    @property
    def rowcount(self) -> int: ...

    def execute(self, sql: str, params: Sequence[Any] = ..., /) -> Any: ...
    def executemany(self, sql: str, params: Sequence[Sequence[Any]], /) -> Any: ...
    def fetchone(self) -> Any: ...
    def fetchall(self) -> list[Any]: ...


class SqlStore(Store):
    dialect: Dialect

    @abstractmethod
    def _transaction(self, lock: Lock | None) -> AbstractContextManager[Cursor]:
        """A cursor inside one transaction, committed on leaving (rolled back on an exception); a write
        transaction (``lock`` given) holds that group's writer lock from its start."""

    def _run(self, cursor: Cursor, statement: str, params: Sequence[Any] = ()) -> Cursor:
        cursor.execute(self.dialect.sql(statement), params)
        return cursor

    # ---- schema ----------------------------------------------------------------------------------------
    def _migrate(self) -> None:
        """Create or bring the schema forward, in one transaction; SchemaTooNew, untouched, if it is newer."""
        with self._transaction("schema") as cursor:
            self._run(cursor, VERSION_TABLE)
            row = self._run(cursor, "SELECT version FROM schema_version WHERE singleton = 1").fetchone()
            found = int(row[0]) if row is not None else 0
            if found > SCHEMA_VERSION:
                raise SchemaTooNew(
                    f"the store {self.location} has schema version {found}, this gcdtrav knows up to "
                    f"{SCHEMA_VERSION}: run a newer gcdtrav (the store is left untouched)"
                )
            for statements in MIGRATIONS[found:]:
                for statement in statements:
                    self._run(cursor, statement)
            if row is None:
                self._run(cursor, "INSERT INTO schema_version (singleton, version) VALUES (1, ?)", (SCHEMA_VERSION,))
            elif found < SCHEMA_VERSION:
                self._run(cursor, "UPDATE schema_version SET version = ? WHERE singleton = 1", (SCHEMA_VERSION,))

    # ---- pairs -----------------------------------------------------------------------------------------
    def append_pairs(
        self,
        pairs: Sequence[PairRecord],
        max_pairs: int,
        max_bytes: int,
        batch_id: str | None = None,
        max_age_s: float | None = None,
        sample_size: int = 0,
    ) -> AppendResult:
        if not pairs:
            return AppendResult(0, 0)
        with self._transaction("pairs") as cursor:
            if batch_id is not None and not self._first_append(cursor, batch_id):
                return AppendResult(0, 0, replayed=True)
            tuple_ids = {key: self._tuple_id(cursor, key) for key in {p.concepts for p in pairs}}
            now = self.clock()
            rows = [
                (tuple_ids[p.concepts], p.source, p.anchor_version, p.kind, float(p.stamp), float(p.outcome),
                 np.asarray(p.weights, "<f4").tobytes(), pair_bytes(len(p.concepts)), p.instance, now,
                 p.graded if p.sums is not None else None)
                for p in pairs
            ]  # fmt: skip
            cursor.executemany(
                self.dialect.sql(
                    "INSERT INTO pairs (tuple_id, source, anchor_version, kind, stamp, outcome, weights, nbytes, "
                    "instance, appended_at, graded) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)"
                ),
                rows,
            )
            graded: dict[tuple[str, str, str, int], list[NDArray[np.float64]]] = {}
            for p in pairs:
                if p.sums is not None and p.graded is not None:
                    graded.setdefault((p.graded, p.anchor_version, p.source, p.kind), []).append(p.sums)
            hour = int(now // 3600)
            for (key, version, source, kind), sums in graded.items():
                self._add_sums(cursor, key, [SumsRow(version, source, kind, hour, np.sum(sums, axis=0))])
            added = sum(row[7] for row in rows)
            self._run(
                cursor,
                "UPDATE pair_totals SET pairs = pairs + ?, bytes = bytes + ? WHERE singleton = 1",
                (len(rows), added),
            )
            if sample_size > 0:
                self._sample(cursor, [(tuple_ids[p.concepts], p) for p in pairs], sample_size)
            evicted = self._evict(cursor, max_pairs, max_bytes)
            if max_age_s is not None:
                evicted += self._evict_older(cursor, now - max_age_s)
        return AppendResult(len(rows), evicted)

    def _sample(self, cursor: Cursor, pairs: Sequence[tuple[int, PairRecord]], size: int) -> None:
        """Reservoir sampling (Vitter's algorithm R) per (tuple, source): after n pairs each is in the sample
        with probability size / n, so the sample spans the whole history, not its last minutes."""
        seen: dict[tuple[int, str], int] = {}
        for key in {(tuple_id, p.source) for tuple_id, p in pairs}:
            row = self._run(
                cursor, "SELECT seen FROM fit_sample_seen WHERE tuple_id = ? AND source = ?", key
            ).fetchone()
            seen[key] = int(row[0]) if row is not None else 0
        slots: dict[tuple[int, str, int], PairRecord] = {}
        for tuple_id, p in pairs:
            key = (tuple_id, p.source)
            seen[key] += 1
            slot = seen[key] - 1 if seen[key] <= size else _RANDOM.randrange(seen[key])
            if slot < size:
                slots[(tuple_id, p.source, slot)] = p
        cursor.executemany(
            self.dialect.sql(
                "INSERT INTO fit_sample (tuple_id, source, slot, anchor_version, kind, stamp, outcome, weights) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?) ON CONFLICT (tuple_id, source, slot) DO UPDATE SET "
                "anchor_version = excluded.anchor_version, kind = excluded.kind, stamp = excluded.stamp, "
                "outcome = excluded.outcome, weights = excluded.weights"
            ),
            [(t, s, slot, p.anchor_version, p.kind, float(p.stamp), float(p.outcome),
              np.asarray(p.weights, "<f4").tobytes()) for (t, s, slot), p in slots.items()],
        )  # fmt: skip
        cursor.executemany(
            self.dialect.sql(
                "INSERT INTO fit_sample_seen (tuple_id, source, seen) VALUES (?, ?, ?) "
                "ON CONFLICT (tuple_id, source) DO UPDATE SET seen = excluded.seen"
            ),
            [(t, s, n) for (t, s), n in seen.items()],
        )

    def sample(self, concepts: Sequence[str]) -> PairColumns:
        key = concept_key(concepts)
        with self._transaction(None) as cursor:
            rows = self._run(
                cursor,
                "SELECT f.slot, f.weights, f.outcome, f.stamp, f.kind, f.anchor_version, f.source, 0, NULL "
                "FROM fit_sample f JOIN concept_tuples t ON t.id = f.tuple_id WHERE t.concepts = ? "
                "ORDER BY f.stamp, f.source, f.slot",
                (json.dumps(list(key)),),
            ).fetchall()
        return _columns(key, rows)

    def _evict_older(self, cursor: Cursor, before: float) -> int:
        """Delete the pairs appended before ``before`` (the age bound); how many went."""
        # 0: written by an instance still running a gcdtrav before 1.7 beside the fleet (its time unknown)
        where = "appended_at > 0 AND appended_at < ?"
        count, size = self._run(
            cursor, f"SELECT count(*), coalesce(sum(nbytes), 0) FROM pairs WHERE {where}", (before,)
        ).fetchone()
        if int(count) == 0:
            return 0
        self._run(cursor, f"DELETE FROM pairs WHERE {where}", (before,))
        self._run(
            cursor,
            "UPDATE pair_totals SET pairs = pairs - ?, bytes = bytes - ? WHERE singleton = 1",
            (int(count), int(size)),
        )
        return int(count)

    def contents(self) -> list[SourceContents]:
        with self._transaction(None) as cursor:
            rows = self._run(
                cursor,
                "SELECT source, count(*), sum(nbytes), min(appended_at), max(appended_at) FROM pairs "
                "GROUP BY source ORDER BY source",
            ).fetchall()
        return [SourceContents(str(s), int(n), int(b), float(lo), float(hi)) for s, n, b, lo, hi in rows]

    def graded_keys(self) -> dict[str, int]:
        with self._transaction(None) as cursor:
            rows = self._run(
                cursor, "SELECT graded, sums FROM calibration_sums WHERE hour = ?", (ALL_HOURS,)
            ).fetchall()
        counts: dict[str, int] = {}
        for key, blob in rows:
            counts[str(key)] = counts.get(str(key), 0) + round(float(_floats(blob)[0]))
        return dict(sorted(counts.items()))

    def _first_append(self, cursor: Cursor, batch_id: str) -> bool:
        """Record the batch's id; False when it was recorded before (a replay). Ids older than a day go: a
        replay comes within the outbox's retry, seconds or minutes later."""
        now = time.time()
        self._run(cursor, "DELETE FROM appended_batches WHERE appended_at < ?", (now - BATCH_IDS_KEPT_S,))
        self._run(
            cursor,
            "INSERT INTO appended_batches (id, appended_at) VALUES (?, ?) ON CONFLICT (id) DO NOTHING",
            (batch_id, now),
        )
        return bool(cursor.rowcount == 1)

    def _tuple_id(self, cursor: Cursor, concepts: tuple[str, ...]) -> int:
        text = json.dumps(list(concepts))
        self._run(cursor, "INSERT INTO concept_tuples (concepts) VALUES (?) ON CONFLICT (concepts) DO NOTHING", (text,))
        return int(self._run(cursor, "SELECT id FROM concept_tuples WHERE concepts = ?", (text,)).fetchone()[0])

    def _evict(self, cursor: Cursor, max_pairs: int, max_bytes: int) -> int:
        """Delete the oldest pairs of the whole store until both bounds hold; how many went."""
        count, size = self._run(cursor, "SELECT pairs, bytes FROM pair_totals WHERE singleton = 1").fetchone()
        count, size = int(count), int(size)
        cut, removed, freed, after = None, 0, 0, -1
        while count - removed > max_pairs or size - freed > max_bytes:
            rows = self._run(
                cursor, "SELECT id, nbytes FROM pairs WHERE id > ? ORDER BY id LIMIT ?", (after, EVICT_CHUNK)
            ).fetchall()
            if not rows:
                break
            for row_id, nbytes in rows:
                if count - removed <= max_pairs and size - freed <= max_bytes:
                    break
                cut, removed, freed = int(row_id), removed + 1, freed + int(nbytes)
            after = int(rows[-1][0])
        if cut is None:
            return 0
        self._run(cursor, "DELETE FROM pairs WHERE id <= ?", (cut,))
        self._run(
            cursor, "UPDATE pair_totals SET pairs = pairs - ?, bytes = bytes - ? WHERE singleton = 1", (removed, freed)
        )
        return removed

    def pairs(
        self,
        concepts: Sequence[str],
        source: str | None = None,
        after_id: int = 0,
        limit: int | None = None,
        newest_first: bool = False,
    ) -> PairColumns:
        key = concept_key(concepts)
        with self._transaction(None) as cursor:
            row = self._run(cursor, "SELECT id FROM concept_tuples WHERE concepts = ?", (json.dumps(list(key)),))
            found = row.fetchone()
            if found is None:
                return PairColumns.empty(key)
            where, params = "tuple_id = ? AND id > ?", list[Any]([int(found[0]), after_id])
            if source is not None:
                where, params = where + " AND source = ?", [*params, source]
            order = "id DESC" if newest_first else "id"
            tail = f" LIMIT {int(limit)}" if limit is not None else ""
            for statement in self.dialect.ordered_read if limit is not None else ():
                self._run(cursor, statement)
            rows = self._run(
                cursor,
                "SELECT id, weights, outcome, stamp, kind, anchor_version, source, appended_at, graded FROM pairs "
                f"WHERE {where} ORDER BY {order}{tail}",
                params,
            ).fetchall()
        return _columns(key, rows[::-1] if newest_first else rows)

    # ---- calibration sums ------------------------------------------------------------------------------
    def _add_sums(self, cursor: Cursor, graded: str, rows: Sequence[SumsRow]) -> None:
        """Add each row to the all-hours sums and, within the last HOURS_KEPT hours, to its hour's (read, add,
        write: writers hold the pairs lock, so no two add at once); older hourly rows go."""
        oldest = int(self.clock() // 3600) - HOURS_KEPT
        for row in rows:
            for hour in (row.hour, ALL_HOURS) if row.hour >= oldest else (ALL_HOURS,):
                key = (graded, hour, row.predicted, row.source, row.kind)
                found = self._run(
                    cursor,
                    "SELECT sums FROM calibration_sums WHERE graded = ? AND hour = ? AND predicted = ? AND source = ? "
                    "AND kind = ?",
                    key,
                ).fetchone()
                total = row.sums + (_floats(found[0]) if found is not None else 0.0)
                self._run(
                    cursor,
                    "INSERT INTO calibration_sums (graded, hour, predicted, source, kind, sums) "
                    "VALUES (?, ?, ?, ?, ?, ?) ON CONFLICT (graded, hour, predicted, source, kind) "
                    "DO UPDATE SET sums = excluded.sums",
                    (*key, np.asarray(total, "<f8").tobytes()),
                )
        self._run(cursor, "DELETE FROM calibration_sums WHERE hour >= 0 AND hour < ?", (oldest,))

    def add_sums(self, graded: str, rows: Sequence[SumsRow], from_id: int, upto_id: int) -> bool:
        with self._transaction("pairs") as cursor:
            found = self._run(cursor, "SELECT upto_id FROM calibration_progress WHERE graded = ?", (graded,))
            row = found.fetchone()
            if (int(row[0]) if row is not None else 0) != from_id:
                return False  # another instance caught up first
            self._add_sums(cursor, graded, rows)
            self._run(
                cursor,
                "INSERT INTO calibration_progress (graded, upto_id) VALUES (?, ?) "
                "ON CONFLICT (graded) DO UPDATE SET upto_id = excluded.upto_id",
                (graded, upto_id),
            )
        return True

    def sums(self, graded: str, since_hour: int | None = None) -> list[SumsRow]:
        where, params = ("hour = ?", [ALL_HOURS]) if since_hour is None else ("hour >= ?", [since_hour])
        with self._transaction(None) as cursor:
            rows = self._run(
                cursor,
                f"SELECT predicted, source, kind, hour, sums FROM calibration_sums WHERE graded = ? AND {where}",
                [graded, *params],
            ).fetchall()
        return [SumsRow(str(v), str(s), int(k), int(h), _floats(b)) for v, s, k, h, b in rows]

    def graded_upto(self, graded: str) -> int:
        with self._transaction(None) as cursor:
            row = self._run(cursor, "SELECT upto_id FROM calibration_progress WHERE graded = ?", (graded,)).fetchone()
        return int(row[0]) if row is not None else 0

    def tuples(self) -> list[tuple[str, ...]]:
        with self._transaction(None) as cursor:
            rows = self._run(
                cursor,
                "SELECT concepts FROM concept_tuples t WHERE EXISTS (SELECT 1 FROM pairs p WHERE p.tuple_id = t.id)",
            ).fetchall()
        return sorted(tuple(json.loads(row[0])) for row in rows)

    def totals(self) -> PairTotals:
        with self._transaction(None) as cursor:
            count, size = self._run(cursor, "SELECT pairs, bytes FROM pair_totals WHERE singleton = 1").fetchone()
        return PairTotals(int(count), int(size))

    # ---- anchor sets -----------------------------------------------------------------------------------
    _HISTORY_COLUMNS = "h.entry, h.version, h.anchor_set, h.accepted_at, h.how, h.forced, h.actor, h.instance"

    def _active(self, cursor: Cursor) -> HistoryRecord | None:
        row = self._run(
            cursor,
            f"SELECT {self._HISTORY_COLUMNS} FROM anchor_active a JOIN anchor_history h ON h.entry = a.entry "
            "WHERE a.singleton = 1",
        ).fetchone()
        return _history_record(row) if row is not None else None

    def active(self) -> HistoryRecord | None:
        with self._transaction(None) as cursor:
            return self._active(cursor)

    def seed(self, anchors: AnchorSet, instance: str, how: str = "seeded", accepted_at: float = 0.0) -> HistoryRecord:
        with self._transaction("anchors") as cursor:
            active = self._active(cursor)
            if active is not None:
                return active
            return self._append_active(cursor, anchors, accepted_at, how, False, "", instance)

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
        when = round(time.time(), 3) if accepted_at is None else accepted_at  # ms: the fleet's tokens carry ms
        with self._transaction("anchors") as cursor:
            active = self._active(cursor)
            if active is not None and expected_active_version is not None and active.version != expected_active_version:
                return Activation(False, active)
            return Activation(True, self._append_active(cursor, anchors, when, how, forced, actor, instance))

    def _append_active(
        self, cursor: Cursor, anchors: AnchorSet, when: float, how: str, forced: bool, actor: str, instance: str
    ) -> HistoryRecord:
        self._run(
            cursor,
            "INSERT INTO anchor_history (version, anchor_set, accepted_at, how, forced, actor, instance) "
            "VALUES (?, ?, ?, ?, ?, ?, ?)",
            (anchors.version, anchors.to_json(), when, how, forced, actor, instance),
        )
        entry = int(self._run(cursor, "SELECT MAX(entry) FROM anchor_history").fetchone()[0])
        updated = self._run(cursor, "UPDATE anchor_active SET entry = ? WHERE singleton = 1", (entry,))
        if _rowcount(updated) == 0:
            self._run(cursor, "INSERT INTO anchor_active (singleton, entry) VALUES (1, ?)", (entry,))
        return HistoryRecord(entry, anchors.version, anchors, when, how, forced, actor, instance)

    def history(self, limit: int = 20) -> list[HistoryRecord]:
        with self._transaction(None) as cursor:
            rows = self._run(
                cursor, f"SELECT {self._HISTORY_COLUMNS} FROM anchor_history h ORDER BY h.entry DESC LIMIT ?", (limit,)
            ).fetchall()
        return [_history_record(row) for row in rows]

    # ---- proposals -------------------------------------------------------------------------------------
    def put_proposal(self, proposal: AnchorProposal, instance: str) -> StoredProposal:
        stored = StoredProposal(proposal.proposed_version, proposal, round(time.time(), 3), instance)
        with self._transaction("anchors") as cursor:
            self._run(cursor, "DELETE FROM anchor_proposals WHERE version = ?", (stored.version,))
            self._run(
                cursor,
                "INSERT INTO anchor_proposals (version, proposal, stored_at, instance) VALUES (?, ?, ?, ?)",
                (stored.version, proposal.model_dump_json(), stored.stored_at, instance),
            )
        return stored

    def proposal(self, version: str) -> StoredProposal | None:
        with self._transaction(None) as cursor:
            row = self._run(
                cursor,
                "SELECT version, proposal, stored_at, instance FROM anchor_proposals WHERE version = ?",
                (version,),
            ).fetchone()
        return _stored_proposal(row) if row is not None else None

    # ---- exclusions ------------------------------------------------------------------------------------
    def exclude(self, exclusion: Exclusion) -> None:
        with self._transaction("anchors") as cursor:
            self._run(
                cursor,
                "INSERT INTO robot_exclusions (robot, excluded, at, actor, reason, instance) VALUES (?, ?, ?, ?, ?, ?)",
                (exclusion.robot, exclusion.excluded, exclusion.at, exclusion.actor, exclusion.reason,
                 exclusion.instance),
            )  # fmt: skip

    def exclusions(self) -> list[Exclusion]:
        with self._transaction(None) as cursor:
            rows = self._run(
                cursor,
                "SELECT robot, excluded, at, actor, reason, instance FROM robot_exclusions e WHERE entry = "
                "(SELECT MAX(entry) FROM robot_exclusions WHERE robot = e.robot) ORDER BY robot",
            ).fetchall()
        return [Exclusion(str(r), bool(x), float(at), str(a), str(why), str(i)) for r, x, at, a, why, i in rows]


def _floats(blob: Any) -> NDArray[np.float64]:
    """Calibration sums as stored (little-endian float64)."""
    return np.frombuffer(bytes(blob), "<f8")


def _rowcount(cursor: Cursor) -> int:
    return int(getattr(cursor, "rowcount", 0))


def _columns(key: tuple[str, ...], rows: list[Any]) -> PairColumns:
    if not rows:
        return PairColumns.empty(key)
    ids, blobs, outcomes, stamps, kinds, versions, sources, appended, graded = zip(*rows, strict=True)
    weights = np.frombuffer(b"".join(bytes(b) for b in blobs), "<f4").reshape(len(rows), len(key))
    return PairColumns(
        concepts=key,
        ids=np.asarray(ids, np.int64),
        weights=weights.astype(np.float32),
        outcomes=np.asarray(outcomes, np.float64),
        stamps=np.asarray(stamps, np.float64),
        kinds=np.asarray(kinds, np.uint8),
        versions=tuple(versions),
        sources=tuple(sources),
        appended_at=np.asarray(appended, np.float64),
        graded=tuple(graded),
    )


def _history_record(row: Sequence[Any]) -> HistoryRecord:
    entry, version, text, accepted_at, how, forced, actor, instance = row
    anchors = AnchorSet.from_text(text, source=f"anchor history entry {entry}")
    return HistoryRecord(int(entry), str(version), anchors, float(accepted_at), str(how), bool(forced), str(actor),
                         str(instance))  # fmt: skip


def _stored_proposal(row: Sequence[Any]) -> StoredProposal:
    version, text, stored_at, instance = row
    return StoredProposal(str(version), AnchorProposal.model_validate_json(text), float(stored_at), str(instance))
