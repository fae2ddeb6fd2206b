"""The outbox between the inference path and the store: pairs wait while PostgreSQL is down (up to the bound,
the rest counted dropped), the status says since when, and all of them are written when it returns; putting
never waits on a busy store; a long read (a calibration) holds nothing an append needs."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import pytest
from gcdtrav.service.store import Store
from gcdtrav.service.store.outbox import PairOutbox, store_status
from gcdtrav.service.store.postgres import ADVISORY_CLASS, ADVISORY_KEYS, PostgresStore
from postgres_cluster import PostgresCluster, postgres_cluster
from store_test_helpers import pair
from zenoh_helpers import wait_until

GRASS = ("grass", "gravel", "rock")


@pytest.fixture
def own_cluster() -> Iterator[PostgresCluster]:
    """A cluster of this test's own: it is stopped and started again."""
    with postgres_cluster() as running:
        yield running


def outbox_of(open_store, bound: int = 100_000) -> PairOutbox:  # type: ignore[no-untyped-def]
    outbox = PairOutbox(open_store, "test", "here", bound, max_pairs=10**6, max_bytes=10**9, retry_s=0.2)
    outbox.open_now()
    outbox.start()
    return outbox


def test_an_outage_keeps_pairs_within_the_bound_and_writes_them_when_the_store_returns(
    own_cluster: PostgresCluster,
) -> None:
    url = own_cluster.create_database("outage")
    outbox = outbox_of(lambda: PostgresStore(url, own_cluster.password, connect_timeout_s=2), bound=50)
    try:
        assert outbox.put([pair(GRASS, k) for k in range(30)]) == 30
        assert outbox.flush(30.0) and outbox.state().written == 30 and outbox.state().reachable
        own_cluster.stop()
        assert outbox.put([pair(GRASS, k) for k in range(30, 70)]) == 40  # waiting, within the bound of 50
        assert wait_until(lambda: not outbox.state().reachable, timeout=30)
        down = outbox.state()
        assert down.unreachable_since is not None and down.error and "outage" in down.error
        assert outbox.put([pair(GRASS, k) for k in range(70, 90)]) == 10  # 50 waiting: the rest dropped
        status = store_status(outbox.state())
        assert not status.reachable and status.pending_pairs == 50 and status.dropped_pairs == 10
        own_cluster.start()
        assert outbox.flush(60.0)
        up = outbox.state()
        assert up.reachable and up.unreachable_since is None and up.written == 80 and up.dropped == 10
        store = outbox.store
        assert store is not None and store.totals().pairs == 80
        assert sorted(store.pairs(GRASS).stamps) == [1000.0 + k for k in range(80)]
    finally:
        outbox.close(timeout_s=5)


def test_a_store_down_at_start_is_opened_when_it_comes(own_cluster: PostgresCluster) -> None:
    url = own_cluster.create_database("late")
    own_cluster.stop()
    outbox = outbox_of(lambda: PostgresStore(url, own_cluster.password, connect_timeout_s=2), bound=10)
    try:
        assert outbox.store is None and not outbox.state().reachable
        assert outbox.put([pair(GRASS, k) for k in range(12)]) == 10
        own_cluster.start()
        assert outbox.flush(60.0) and outbox.store is not None and outbox.store.totals().pairs == 10
    finally:
        outbox.close(timeout_s=5)


def test_put_never_waits_on_a_busy_store(cluster: PostgresCluster) -> None:
    """Another session holds the pairs' writer lock: the writer's append waits on it; putting does not."""
    import psycopg

    url = cluster.create_database("busy")
    outbox = outbox_of(lambda: PostgresStore(url, cluster.password))
    blocker = psycopg.connect(url, password=cluster.password)
    try:
        blocker.execute("SELECT pg_advisory_xact_lock(%s, %s)", (ADVISORY_CLASS, ADVISORY_KEYS["pairs"]))
        outbox.put([pair(GRASS, 0)])
        assert wait_until(lambda: outbox.state().pending == 1 and not outbox.flush(0.1), timeout=60)
        for k in range(1, 200):  # the writer is stuck in its transaction: every put still returns
            assert outbox.put([pair(GRASS, k)]) == 1
        assert outbox.pending == 200
        blocker.rollback()  # the lock goes
        assert outbox.flush(30.0) and outbox.state().written == 200
    finally:
        blocker.close()
        outbox.close(timeout_s=5)


def test_a_long_read_holds_nothing_an_append_needs(open_same_store) -> None:  # type: ignore[no-untyped-def]
    reader: Store = open_same_store()
    reader.append_pairs([pair(GRASS, k) for k in range(1000)], 10**6, 10**9)
    outbox = outbox_of(open_same_store)
    inside, finished = threading.Event(), threading.Event()

    def calibrate() -> None:
        with reader._transaction(None) as cursor:  # type: ignore[attr-defined]
            cursor.execute("SELECT weights FROM pairs")
            cursor.fetchall()
            inside.set()
            finished.wait(30)  # a calibration still reading

    thread = threading.Thread(target=calibrate)
    thread.start()
    try:
        assert inside.wait(30)
        assert outbox.put([pair(GRASS, 5000 + k) for k in range(100)]) == 100
        assert outbox.flush(30.0)  # written while the read is open
        assert outbox.store is not None and outbox.store.totals().pairs == 1100
    finally:
        finished.set()
        thread.join()
        outbox.close(timeout_s=5)
