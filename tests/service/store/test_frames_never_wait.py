"""The inference path never waits on the store: a swap stuck in the database (another session holds the
anchors' writer lock, as a slow or busy PostgreSQL would) leaves the frame's triage, which asks the anchor
switch for the active version, and the status answering at once; the swap completes when the database does."""

from __future__ import annotations

import threading

from gcdtrav.schemas.anchors import Anchor, AnchorSet
from gcdtrav.schemas.config import EngineSettings
from gcdtrav.service.pipeline import Pipeline
from gcdtrav.service.runtime.fleet.anchor_switch import AnchorSwitch
from gcdtrav.service.store.postgres import ADVISORY_CLASS, ADVISORY_KEYS, PostgresStore
from postgres_cluster import PostgresCluster
from zenoh_helpers import wait_until

from tools.synthetic_scene import SceneBackend, start_anchors


def test_a_swap_waiting_on_the_database_blocks_no_reader_of_the_active_set(cluster: PostgresCluster) -> None:
    import psycopg

    url = cluster.create_database("frames")
    store = PostgresStore(url, cluster.password)
    start = start_anchors()
    switch = AnchorSwitch(Pipeline(SceneBackend(), start, EngineSettings()), store, "box", 65536)
    other = AnchorSet(anchors=[Anchor(concept="grass", position=0.2), Anchor(concept="sand", position=0.9)])
    blocker = psycopg.connect(url, password=cluster.password)
    done = threading.Event()
    try:
        blocker.execute("SELECT pg_advisory_xact_lock(%s, %s)", (ADVISORY_CLASS, ADVISORY_KEYS["anchors"]))
        switch.submit(other.to_json().encode(), lambda anchors, error: done.set())
        assert wait_until(lambda: switch._lock.locked(), timeout=60)  # the swap is inside, waiting on the store
        answered: list[str] = []  # what a frame's triage and a status ask meanwhile: answered, the start set
        reader = threading.Thread(target=lambda: answered.extend(switch.head().version for _ in range(100)))
        reader.start()
        reader.join(timeout=60)
        assert answered == [start.version] * 100 and not done.is_set()
        blocker.rollback()
        assert done.wait(30) and switch.head().version == other.version
    finally:
        blocker.close()
        switch.close()
        store.close()
