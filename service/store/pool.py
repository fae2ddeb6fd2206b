"""A small connection pool: at most ``size`` connections, each lent for one transaction (issue 57).

A fleet's instances share one PostgreSQL server, whose ``max_connections`` is finite: with a connection per
thread the fleet's count was its instances times their threads, unstated. Lent per transaction, an instance
never holds more than ``size``; a call finding all of them busy waits up to ``wait_s``, then gets
``StoreUnavailable`` (the outbox retries appends; a report's query answers with the error)."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Generic, TypeVar

from gcdtrav.service.store.records import StoreError, StoreUnavailable

Connection = TypeVar("Connection")


class Lent(Generic[Connection]):
    """One transaction's connection: opened on first use; ``forget`` drops a failed one (the next use opens
    another)."""

    def __init__(self, pool: ConnectionPool[Connection], connection: Connection | None) -> None:
        self._pool, self._connection = pool, connection

    @property
    def connection(self) -> Connection:
        if self._connection is None:
            self._connection = self._pool.open_connection()
        return self._connection

    def forget(self) -> None:
        if self._connection is not None:
            self._pool.close_connection(self._connection)
            self._connection = None

    def give_back(self) -> Connection | None:
        connection, self._connection = self._connection, None
        return connection


class ConnectionPool(Generic[Connection]):
    def __init__(
        self,
        location: str,
        open_connection: Callable[[], Connection],
        close_connection: Callable[[Connection], None],
        usable: Callable[[Connection], bool],
        size: int,
        wait_s: float,
    ) -> None:
        self.location, self.size, self.wait_s = location, size, wait_s
        self.open_connection, self.close_connection, self._usable = open_connection, close_connection, usable
        self._free = threading.BoundedSemaphore(size)
        self._idle: list[Connection] = []
        self._lock = threading.Lock()
        self._closed = False

    @contextmanager
    def lent(self) -> Iterator[Lent[Connection]]:
        """A connection for one transaction (an idle one if usable, else a new one), given back afterwards."""
        self._refuse_if_closed()
        if not self._free.acquire(timeout=self.wait_s):
            raise StoreUnavailable(
                f"the store {self.location}: all {self.size} pooled connections stayed busy for {self.wait_s:g} s"
            )
        lent = Lent(self, self._idle_connection())
        try:
            yield lent
        finally:
            self._give_back(lent.give_back())
            self._free.release()

    def _idle_connection(self) -> Connection | None:
        while True:
            with self._lock:
                connection = self._idle.pop() if self._idle else None
            if connection is None or self._usable(connection):
                return connection
            self.close_connection(connection)

    def _give_back(self, connection: Connection | None) -> None:
        if connection is None:
            return
        with self._lock:
            keep = not self._closed
            if keep:
                self._idle.append(connection)
        if not keep:
            self.close_connection(connection)

    def close(self) -> None:
        """Close the idle connections now, and the lent ones as they come back; the pool lends no more."""
        with self._lock:
            self._closed = True
            idle, self._idle = self._idle, []
        for connection in idle:
            self.close_connection(connection)

    def _refuse_if_closed(self) -> None:
        if self._closed:
            raise StoreError(f"the store {self.location} is closed")
