"""Fixtures of the store's test suite (tests/service/store/), run against both backends: ``store`` is a fresh
SQLite file or a fresh database in one throw-away PostgreSQL cluster (tests/postgres_cluster.py; skipped
locally without PostgreSQL, a failure in CI). A plugin of tests/conftest.py: a second conftest.py would
replace the root one as ``conftest`` (``from conftest import ...`` in other tests)."""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from gcdtrav.service.store import Store
from gcdtrav.service.store.postgres import PostgresStore
from gcdtrav.service.store.sqlite import SqliteStore
from postgres_cluster import PostgresCluster, postgres_cluster

_databases = itertools.count()
OpenStore = Callable[[], Store]


@pytest.fixture(scope="session")
def cluster() -> Iterator[PostgresCluster]:
    with postgres_cluster() as running:
        yield running


@pytest.fixture(params=["sqlite", "postgresql"])
def open_same_store(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[OpenStore]:
    """Opens one and the same (initially empty) store, as often as asked: a second instance of the fleet, or a
    restart. Every store opened is closed afterwards."""
    opened: list[Store] = []
    if request.param == "sqlite":
        path = tmp_path / "gcdtrav.store.sqlite3"

        def opener() -> Store:
            opened.append(SqliteStore(path))
            return opened[-1]
    else:
        running: PostgresCluster = request.getfixturevalue("cluster")
        url = running.create_database(f"store_{next(_databases)}")

        def opener() -> Store:
            opened.append(PostgresStore(url, running.password))
            return opened[-1]

    yield opener
    for store in opened:
        store.close()


@pytest.fixture
def store(open_same_store: OpenStore) -> Store:
    return open_same_store()
