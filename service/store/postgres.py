"""A fleet's store: one PostgreSQL database every instance shares (psycopg 3, in the ``gcdtrav[service]``
extra). A small pool per instance (``ConnectionPool``, ``store.pool_size``, 3): a connection is lent for one
transaction, so the server sees at most instances x pool_size connections from the fleet, whatever the threads
(docs/kubernetes.md gives max_connections). Autocommit with explicit transactions; a write
transaction first takes a transaction-scoped advisory lock of its table group, so appends from every instance
keep one fleet-wide order and bounds, and of two activations exactly one sees the other's result.

A connection that fails is dropped and made again at the next call: a database restarted under a running
fleet costs the calls made while it was down (``StoreUnavailable``), nothing else. The password is given to
libpq apart from the URL and scrubbed from any message that might echo it."""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from typing import Any

from gcdtrav.service.store.pool import ConnectionPool, Lent
from gcdtrav.service.store.records import StoreError, StoreUnavailable
from gcdtrav.service.store.schema import POSTGRESQL
from gcdtrav.service.store.sql import Cursor, Lock, SqlStore

ADVISORY_CLASS = 0x6763  # 'gc': the first key of gcdtrav's advisory locks
ADVISORY_KEYS: dict[Lock, int] = {"schema": 1, "pairs": 2, "anchors": 3}


def _psycopg() -> Any:
    try:
        import psycopg
    except ImportError:
        raise StoreError(
            "store: url names PostgreSQL, but psycopg is not installed: pip install 'gcdtrav[service]'"
        ) from None
    return psycopg


class PostgresStore(SqlStore):
    backend = "postgresql"
    dialect = POSTGRESQL

    def __init__(
        self,
        url: str,
        password: str | None,
        connect_timeout_s: float = 5.0,
        pool_size: int = 3,
        pool_wait_s: float = 10.0,
    ) -> None:
        self.url = url
        self._password = password
        self._timeout = max(2, math.ceil(connect_timeout_s))  # libpq's connect_timeout: whole seconds, 2 at least
        self._psycopg = _psycopg()
        self._pool: ConnectionPool[Any] = ConnectionPool(
            url, self._connect, self._close_quietly, lambda c: not c.closed and not c.broken, pool_size, pool_wait_s
        )
        self._migrate()

    @property
    def location(self) -> str:
        return self.url  # holds no password: the settings refuse one in the URL

    def _connect(self) -> Any:
        extra = {"password": self._password} if self._password is not None else {}
        try:
            connection = self._psycopg.connect(
                self.url, autocommit=True, connect_timeout=self._timeout, application_name="gcdtrav", **extra
            )
        except self._psycopg.Error as err:
            raise self._error(err) from None
        return connection

    def _close_quietly(self, connection: Any) -> None:
        with suppress(self._psycopg.Error):
            connection.close()

    @contextmanager
    def _transaction(self, lock: Lock | None) -> Iterator[Cursor]:
        with self._pool.lent() as lent:
            connection = self._begun(lent)
            try:
                with connection.cursor() as cursor:
                    if lock is not None:
                        cursor.execute("SELECT pg_advisory_xact_lock(%s, %s)", (ADVISORY_CLASS, ADVISORY_KEYS[lock]))
                    yield cursor
                connection.execute("COMMIT")
            except BaseException as err:
                if not connection.broken:
                    with suppress(self._psycopg.Error):
                        connection.execute("ROLLBACK")
                if not isinstance(err, self._psycopg.Error):
                    raise
                if connection.broken or isinstance(err, self._psycopg.OperationalError):
                    lent.forget()
                raise self._error(err) from None

    def _begun(self, lent: Lent[Any]) -> Any:
        """The lent connection inside a new transaction; on a fresh connection if the kept one fails at BEGIN
        (the server restarted since it was used: nothing was done, so trying again is safe)."""
        try:
            lent.connection.execute("BEGIN")
            return lent.connection
        except self._psycopg.Error:
            lent.forget()
        try:
            lent.connection.execute("BEGIN")
        except self._psycopg.Error as err:
            lent.forget()
            raise self._error(err) from None
        return lent.connection

    def _error(self, err: Exception) -> StoreError:
        """One line, the password scrubbed; connection trouble is StoreUnavailable (retried later)."""
        detail = " ".join(str(err).split())
        if self._password:
            detail = detail.replace(self._password, "***")
        message = f"the store {self.url}: {detail}"
        if isinstance(err, self._psycopg.OperationalError | self._psycopg.InterfaceError):
            return StoreUnavailable(message)
        return StoreError(message)

    def close(self) -> None:
        self._pool.close()
