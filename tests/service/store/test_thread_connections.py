"""ThreadConnections: the one per-thread connection bookkeeping both store backends use."""

from __future__ import annotations

import threading

import pytest
from gcdtrav.service.store.records import StoreError
from gcdtrav.service.store.sql import ThreadConnections


class Connection:
    def __init__(self, number: int) -> None:
        self.number = number
        self.closed = False


class Maker:
    def __init__(self) -> None:
        self.made: list[Connection] = []

    def open(self) -> Connection:
        self.made.append(Connection(len(self.made)))
        return self.made[-1]

    @staticmethod
    def close(connection: Connection) -> None:
        connection.closed = True


def connections(maker: Maker) -> ThreadConnections[Connection]:
    return ThreadConnections("test.db", maker.open, maker.close, usable=lambda c: not c.closed)


def test_one_connection_per_thread_kept_between_calls() -> None:
    maker = Maker()
    kept = connections(maker)
    mine = kept.get()
    assert kept.get() is mine
    theirs: list[Connection] = []
    worker = threading.Thread(target=lambda: theirs.append(kept.get()))
    worker.start()
    worker.join()
    assert theirs[0] is not mine and len(maker.made) == 2


def test_close_closes_every_thread_connection_and_refuses_new_ones() -> None:
    maker = Maker()
    kept = connections(maker)
    kept.get()
    worker = threading.Thread(target=kept.get)
    worker.start()
    worker.join()
    kept.close()
    assert all(c.closed for c in maker.made) and len(maker.made) == 2
    with pytest.raises(StoreError, match=r"the store test\.db is closed"):
        kept.get()


def test_a_forgotten_connection_is_closed_and_replaced() -> None:
    maker = Maker()
    kept = connections(maker)
    broken = kept.get()
    kept.forget(broken)
    assert broken.closed
    fresh = kept.get()
    assert fresh is not broken
    kept.close()
    assert fresh.closed


def test_an_unusable_kept_connection_is_replaced() -> None:
    maker = Maker()
    kept = connections(maker)
    first = kept.get()
    first.closed = True  # the server went away under it
    assert kept.get() is not first


def test_a_connection_made_while_the_store_closes_is_closed_not_leaked() -> None:
    maker = Maker()
    kept: ThreadConnections[Connection]

    def open_then_close_store() -> Connection:
        connection = maker.open()
        kept.close()  # another thread closes the store while this connection is being made
        return connection

    kept = ThreadConnections("test.db", open_then_close_store, maker.close)
    with pytest.raises(StoreError, match="closed"):
        kept.get()
    assert maker.made[0].closed
