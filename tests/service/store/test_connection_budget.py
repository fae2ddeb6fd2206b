"""The connection budget (issue 57): 8 instances against one PostgreSQL whose max_connections is exactly
8 x pool_size (+ 1 for this test's watcher). Each instance appends through its outbox while two more threads
read reports and history, more threads than pooled connections: no connection is refused, the server never
sees more than 8 x pool_size of the fleet's, and no pair is lost."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.service.store import PairRecord, StoreError
from gcdtrav.service.store.outbox import PairOutbox
from gcdtrav.service.store.postgres import PostgresStore
from postgres_cluster import postgres_cluster

INSTANCES, POOL, BATCHES, BATCH = 8, 2, 15, 40
CONCEPTS = ("grass", "gravel", "rock")


def batch(instance: int, k: int) -> list[PairRecord]:
    weights = np.full(3, 1 / 3, np.float32)
    return [PairRecord(CONCEPTS, weights, 0.5, 1000.0 + k, 0, "v1", f"r{instance}", f"i{instance}")
            for _ in range(BATCH)]  # fmt: skip


def test_eight_instances_stay_within_their_pools_and_lose_no_pair() -> None:
    with postgres_cluster(max_connections=INSTANCES * POOL + 1) as cluster:
        import psycopg

        url = cluster.create_database("budget")
        watcher = psycopg.connect(url, password=cluster.password, autocommit=True)
        seen: list[int] = []
        errors: list[Exception] = []
        done = threading.Event()

        def watch() -> None:
            while not done.is_set():
                row = watcher.execute("SELECT count(*) FROM pg_stat_activity WHERE application_name = 'gcdtrav'")
                seen.append(int(row.fetchone()[0]))  # type: ignore[index]
                time.sleep(0.02)

        def opener(index: int):  # type: ignore[no-untyped-def]
            return lambda: PostgresStore(url, cluster.password, pool_size=POOL, pool_wait_s=30.0)

        outboxes = [PairOutbox(opener(i), "postgresql", url, 100_000, 10**7, 10**9) for i in range(INSTANCES)]
        for outbox in outboxes:
            assert outbox.open_now() is not None
            outbox.start()

        def read(outbox: PairOutbox) -> None:
            anchors = default_anchor_set()
            while not done.is_set():
                try:
                    assert outbox.store is not None
                    outbox.store.pairs(CONCEPTS)
                    outbox.store.history()
                    outbox.store.exclusions()
                    outbox.store.seed(anchors, "reader")
                except StoreError as err:
                    errors.append(err)

        threads = [threading.Thread(target=watch)]
        threads += [threading.Thread(target=read, args=(o,)) for o in outboxes for _ in range(2)]
        for thread in threads:
            thread.start()
        for k in range(BATCHES):
            for index, outbox in enumerate(outboxes):
                assert outbox.put(batch(index, k)) == BATCH
        assert all(outbox.flush(60.0) for outbox in outboxes)
        done.set()
        for thread in threads:
            thread.join(30)
        for outbox in outboxes:
            outbox.close()
        stored = watcher.execute("SELECT count(*), count(DISTINCT source) FROM pairs").fetchone()
        watcher.close()
    assert errors == [], errors[:3]
    assert stored == (INSTANCES * BATCHES * BATCH, INSTANCES)
    assert max(seen) <= INSTANCES * POOL, max(seen)
    assert max(seen) > INSTANCES  # the readers did run beside the writers


def test_a_pool_whose_connections_stay_busy_says_so(tmp_path: object) -> None:
    with postgres_cluster() as cluster:
        url = cluster.create_database("busy")
        store = PostgresStore(url, cluster.password, pool_size=1, pool_wait_s=0.2)
        try:
            with store._pool.lent() as lent:  # the one connection, held
                assert lent.connection is not None
                with pytest.raises(StoreError, match=r"all 1 pooled connections stayed busy for 0\.2 s"):
                    store.history()
            assert store.history() is not None  # given back: usable again
        finally:
            store.close()
