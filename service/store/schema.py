"""The one schema both backends hold, and its migrations, forward only.

Each migration is the statements that take the schema from its index to the next version; the types are
written as {id}, {float} and {blob} and filled in per backend. A store whose ``schema_version`` is above
``SCHEMA_VERSION`` was written by a newer gcdtrav: it is refused untouched (``SchemaTooNew``), never downgraded.
"""

from __future__ import annotations

from dataclasses import dataclass

SCHEMA_VERSION = 4


@dataclass(frozen=True)
class Dialect:
    name: str
    id: str  # an auto-incrementing 64-bit primary key
    float: str
    blob: str
    placeholder: str
    # Run before reading a tuple's first or last N pairs: PostgreSQL's planner, with statistics behind a fast
    # growing table (autovacuum analyses a minute later), took a bitmap scan and sorted every pair of the tuple
    # (113 ms at 3 x 10^5 pairs) where the (tuple_id, id) index gives them in order (4 ms).
    ordered_read: tuple[str, ...] = ()
    now: str = "CAST(strftime('%s', 'now') AS REAL)"

    def sql(self, statement: str) -> str:
        """A statement written with ``?`` placeholders, {id}/{float}/{blob} types and {now} (the server's time,
        s since the epoch), in this dialect."""
        typed = statement.format(id=self.id, float=self.float, blob=self.blob, now=self.now)
        return typed.replace("?", self.placeholder) if self.placeholder != "?" else typed


SQLITE = Dialect("sqlite", "INTEGER PRIMARY KEY AUTOINCREMENT", "REAL", "BLOB", "?")
POSTGRESQL = Dialect(
    "postgresql", "BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY", "DOUBLE PRECISION", "BYTEA", "%s",
    ("SET LOCAL enable_bitmapscan = off",), "EXTRACT(EPOCH FROM now())",
)  # fmt: skip

VERSION_TABLE = (
    "CREATE TABLE IF NOT EXISTS schema_version "
    "(singleton INTEGER PRIMARY KEY CHECK (singleton = 1), version INTEGER NOT NULL)"
)

MIGRATIONS: tuple[tuple[str, ...], ...] = (
    # 0 -> 1: pairs (with their concept tuples and fleet-wide totals), anchor history, the active pointer,
    # kept proposals.
    (
        "CREATE TABLE concept_tuples (id {id}, concepts TEXT NOT NULL UNIQUE)",
        "CREATE TABLE pairs (id {id}, tuple_id BIGINT NOT NULL REFERENCES concept_tuples (id), "
        "source TEXT NOT NULL, anchor_version TEXT NOT NULL, kind SMALLINT NOT NULL, stamp {float} NOT NULL, "
        "outcome {float} NOT NULL, weights {blob} NOT NULL, nbytes INTEGER NOT NULL, instance TEXT NOT NULL)",
        "CREATE INDEX pairs_by_tuple ON pairs (tuple_id, id)",
        "CREATE TABLE pair_totals (singleton INTEGER PRIMARY KEY CHECK (singleton = 1), "
        "pairs BIGINT NOT NULL, bytes BIGINT NOT NULL)",
        "INSERT INTO pair_totals (singleton, pairs, bytes) VALUES (1, 0, 0)",
        "CREATE TABLE anchor_history (entry {id}, version TEXT NOT NULL, anchor_set TEXT NOT NULL, "
        "accepted_at {float} NOT NULL, how TEXT NOT NULL, forced BOOLEAN NOT NULL, actor TEXT NOT NULL, "
        "instance TEXT NOT NULL)",
        "CREATE TABLE anchor_active (singleton INTEGER PRIMARY KEY CHECK (singleton = 1), "
        "entry BIGINT NOT NULL REFERENCES anchor_history (entry))",
        "CREATE TABLE anchor_proposals (id {id}, version TEXT NOT NULL UNIQUE, proposal TEXT NOT NULL, "
        "stored_at {float} NOT NULL, instance TEXT NOT NULL)",
    ),
    # 1 -> 2: the batches appended, by id: a batch replayed after its commit's answer was lost stores nothing.
    (
        "CREATE TABLE appended_batches (id TEXT PRIMARY KEY, appended_at {float} NOT NULL)",
        "CREATE INDEX appended_batches_by_time ON appended_batches (appended_at)",
    ),
    # 2 -> 3: operators' exclusions of a robot's pairs (issue 58), every word kept, the newest in force.
    (
        "CREATE TABLE robot_exclusions (entry {id}, robot TEXT NOT NULL, excluded BOOLEAN NOT NULL, "
        "at {float} NOT NULL, actor TEXT NOT NULL, reason TEXT NOT NULL, instance TEXT NOT NULL)",
    ),
    # 3 -> 4: calibration kept as sums (issue 57): per grading version, predicting version, source, kind and
    # hour of appending (hour -1: all hours), updated in the append's transaction; how far the catch-up of a
    # version's sums over older pairs came; when a pair was appended and which version graded it then.
    (
        "ALTER TABLE pairs ADD COLUMN appended_at {float} NOT NULL DEFAULT 0",
        "UPDATE pairs SET appended_at = {now}",  # the pairs already kept: appended (at the latest) now
        "ALTER TABLE pairs ADD COLUMN graded TEXT",
        "CREATE INDEX pairs_by_appended ON pairs (appended_at)",
        "CREATE TABLE calibration_sums (graded TEXT NOT NULL, predicted TEXT NOT NULL, source TEXT NOT NULL, "
        "kind SMALLINT NOT NULL, hour BIGINT NOT NULL, sums {blob} NOT NULL, "
        "PRIMARY KEY (graded, hour, predicted, source, kind))",
        "CREATE INDEX calibration_sums_by_hour ON calibration_sums (hour)",  # old hourly rows found, not scanned
        "CREATE TABLE calibration_progress (graded TEXT PRIMARY KEY, upto_id BIGINT NOT NULL)",
        # the fitting sample: a uniform reservoir of each (tuple, source)'s whole history, pairs copied in
        "CREATE TABLE fit_sample (tuple_id BIGINT NOT NULL, source TEXT NOT NULL, slot INTEGER NOT NULL, "
        "anchor_version TEXT NOT NULL, kind SMALLINT NOT NULL, stamp {float} NOT NULL, outcome {float} NOT NULL, "
        "weights {blob} NOT NULL, PRIMARY KEY (tuple_id, source, slot))",
        "CREATE TABLE fit_sample_seen (tuple_id BIGINT NOT NULL, source TEXT NOT NULL, seen BIGINT NOT NULL, "
        "PRIMARY KEY (tuple_id, source))",
    ),
)
assert len(MIGRATIONS) == SCHEMA_VERSION
