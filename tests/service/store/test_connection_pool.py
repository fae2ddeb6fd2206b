"""ConnectionPool: the one connection bookkeeping both store backends use (a connection lent per transaction,
at most ``size`` of them)."""

from __future__ import annotations

import threading
import time

import pytest
from gcdtrav.service.store.pool import ConnectionPool
from gcdtrav.service.store.records import StoreError, StoreUnavailable


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


def pool(maker: Maker, size: int = 2, wait_s: float = 5.0) -> ConnectionPool[Connection]:
    return ConnectionPool("test.db", maker.open, maker.close, lambda c: not c.closed, size, wait_s)


def test_a_connection_is_kept_between_transactions_and_never_more_than_size_exist() -> None:
    maker = Maker()
    lender = pool(maker, size=2)
    with lender.lent() as lent:
        first = lent.connection
    with lender.lent() as lent:
        assert lent.connection is first
    held = threading.Barrier(3)
    release = threading.Event()

    def hold() -> None:
        with lender.lent() as lent:
            assert lent.connection is not None
            held.wait()
            release.wait(5)

    workers = [threading.Thread(target=hold) for _ in range(2)]
    for worker in workers:
        worker.start()
    held.wait()
    started = time.monotonic()
    waited: list[float] = []

    def third_call() -> None:
        with lender.lent():
            waited.append(time.monotonic() - started)

    third = threading.Thread(target=third_call)
    third.start()
    time.sleep(0.3)
    assert waited == []  # both connections lent: the third call waits
    release.set()
    for worker in (*workers, third):
        worker.join(5)
    assert waited and waited[0] >= 0.3 and len(maker.made) == 2


def test_all_connections_busy_past_the_wait_is_unavailable_naming_the_pool() -> None:
    lender = pool(Maker(), size=1, wait_s=0.1)
    busy = pytest.raises(StoreUnavailable, match=r"all 1 pooled connections stayed busy for 0\.1 s")
    with lender.lent(), busy, lender.lent():
        pass


def test_close_closes_idle_and_returning_connections_and_refuses_new_ones() -> None:
    maker = Maker()
    lender = pool(maker)
    with lender.lent() as lent:
        assert lent.connection is not None
    with lender.lent() as lent:
        busy = lent.connection
        lender.close()  # another thread closes the store while this transaction runs
        assert maker.made[0] is busy and not busy.closed
    assert busy.closed
    with pytest.raises(StoreError, match=r"the store test\.db is closed"), lender.lent():
        pass


def test_a_forgotten_connection_is_closed_and_replaced() -> None:
    maker = Maker()
    lender = pool(maker)
    with lender.lent() as lent:
        broken = lent.connection
        lent.forget()
        assert broken.closed
        fresh = lent.connection
    assert fresh is not broken
    with lender.lent() as lent:
        assert lent.connection is fresh


def test_an_unusable_idle_connection_is_replaced() -> None:
    maker = Maker()
    lender = pool(maker)
    with lender.lent() as lent:
        first = lent.connection
    first.closed = True  # the server went away under it
    with lender.lent() as lent:
        assert lent.connection is not first
