"""The embedded store: one SQLite file in the state dir (the standard library's sqlite3, WAL), so a single box
needs nothing set up. Connections lent per transaction from a small pool (``pool.ConnectionPool``, as for
PostgreSQL); writers take SQLite's one writer lock (BEGIN IMMEDIATE), readers run beside them (WAL)."""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from gcdtrav.service.store.pool import ConnectionPool
from gcdtrav.service.store.records import StoreError, StoreUnavailable
from gcdtrav.service.store.schema import SQLITE
from gcdtrav.service.store.sql import Cursor, Lock, SqlStore

BUSY_TIMEOUT_S = 30.0  # another writer (a second process on the same file) holds the lock this long at most
POOL_SIZE = 4  # the outbox's writer, the anchor switch's reader and worker, one more (a status, a tool)


class SqliteStore(SqlStore):
    backend = "sqlite"
    dialect = SQLITE

    def __init__(self, path: Path) -> None:
        self.path = path
        self._pool = ConnectionPool(
            str(path), self._connect, sqlite3.Connection.close, lambda _: True, POOL_SIZE, BUSY_TIMEOUT_S
        )
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise StoreUnavailable(f"cannot create the folder of the store {path}: {err.strerror or err}") from None
        self._migrate()

    @property
    def location(self) -> str:
        return str(self.path)

    def _connect(self) -> sqlite3.Connection:
        try:
            connection = sqlite3.connect(
                self.path, timeout=BUSY_TIMEOUT_S, isolation_level=None, check_same_thread=False
            )
            connection.execute("PRAGMA journal_mode=WAL")
            connection.execute("PRAGMA synchronous=FULL")  # a committed pair survives a power cut
            connection.execute("PRAGMA foreign_keys=ON")
        except sqlite3.Error as err:
            raise _store_error(self.path, err) from None
        return connection

    @contextmanager
    def _transaction(self, lock: Lock | None) -> Iterator[Cursor]:
        with self._pool.lent() as lent:
            connection = lent.connection
            try:
                cursor = connection.cursor()
                cursor.execute("BEGIN IMMEDIATE" if lock is not None else "BEGIN")
                try:
                    yield cursor
                except BaseException:
                    connection.rollback()
                    raise
                connection.commit()
            except sqlite3.Error as err:
                if connection.in_transaction:
                    connection.rollback()
                raise _store_error(self.path, err) from None

    def close(self) -> None:
        self._pool.close()


def _store_error(path: Path, err: sqlite3.Error) -> StoreError:
    """Locked, full, read-only, unreadable or corrupt files may heal or be replaced (the service serves on, its
    pairs waiting; retried later); anything else (a refused row) is a plain error."""
    message = f"the store {path}: {err}"
    unusable = isinstance(err, sqlite3.OperationalError) or type(err) is sqlite3.DatabaseError
    return StoreUnavailable(message) if unusable else StoreError(message)
