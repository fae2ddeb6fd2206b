"""``store:``: strict, SQLite by default; PostgreSQL's password only from a file or the environment, and never
in an error, a log line or the status."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
from gcdtrav.schemas.settings import ServiceSettings, SettingsError, StoreSettings, load_settings
from gcdtrav.schemas.settings.store import PASSWORD_ENV
from gcdtrav.service.store import SchemaTooNew, StoreError, StoreUnavailable, open_store, store_password
from gcdtrav.service.store.opening import service_outbox
from gcdtrav.service.store.outbox import store_status
from gcdtrav.service.store.schema import SCHEMA_VERSION
from gcdtrav.service.store.sqlite import SqliteStore
from postgres_cluster import PostgresCluster


def test_no_setting_is_sqlite_in_the_state_dir(tmp_path: Path) -> None:
    store = open_store(StoreSettings(), tmp_path, "site/a")
    try:
        assert isinstance(store, SqliteStore) and store.path == tmp_path / "site_a.store.sqlite3"
    finally:
        store.close()


@pytest.mark.parametrize(
    ("store", "message"),
    [
        ({"url": "postgresql://gcdtrav:hunter2@db:5432/gcdtrav"}, "url holds a password"),
        ({"url": "mysql://db/gcdtrav"}, "must start with postgresql://"),
        ({"url": "postgresql://db:99999/x"}, "not a URL"),
        ({"outbox_pairs": 0}, "greater than or equal to 1"),
        ({"retry_s": 0}, "greater than 0"),
        ({"password": "x"}, "Extra inputs"),
    ],
)
def test_bad_store_settings_are_refused(store: dict[str, object], message: str) -> None:
    """As `gcdtrav serve` loads them: one error naming the field, never echoing the value."""
    with pytest.raises(SettingsError, match=message) as refused:
        load_settings(None, {"store": store}, environ={})
    assert "hunter2" not in str(refused.value) and "store." in str(refused.value)


def test_the_edges_that_are_allowed() -> None:
    settings = ServiceSettings.model_validate({"store": {"url": "postgres://gcdtrav@db/x", "outbox_pairs": 1}})
    assert settings.store.url is not None and settings.store.outbox_pairs == 1


def test_the_password_comes_from_its_file_else_the_environment(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    secret = tmp_path / "password"
    secret.write_text("s3cret\n")
    from_file = StoreSettings(url="postgresql://gcdtrav@db/x", password_file=secret)
    assert store_password(from_file, {PASSWORD_ENV: "other"}) == "s3cret"
    assert store_password(StoreSettings(url="postgresql://gcdtrav@db/x"), {PASSWORD_ENV: "env"}) == "env"
    assert store_password(StoreSettings(url="postgresql://gcdtrav@db/x"), {}) is None
    missing = StoreSettings(url="postgresql://gcdtrav@db/x", password_file=tmp_path / "none")
    with pytest.raises(StoreError, match="cannot read password_file"):
        store_password(missing)
    with caplog.at_level(logging.WARNING):  # the secret's variable is not taken for an unknown setting
        load_settings(None, environ={PASSWORD_ENV: "env"})
    assert not caplog.records


def test_a_wrong_password_never_shows_in_errors_logs_or_status(
    cluster: PostgresCluster, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    url = cluster.create_database("passwords")
    wrong = "wrong-" + cluster.password
    monkeypatch.setenv(PASSWORD_ENV, wrong)
    settings = ServiceSettings.model_validate({"state_dir": tmp_path, "store": {"url": url, "connect_timeout_s": 2}})
    with pytest.raises(StoreUnavailable) as refused:
        open_store(settings.store, tmp_path, "gcdtrav")
    assert "password authentication failed" in str(refused.value) and wrong not in str(refused.value)
    with caplog.at_level(logging.DEBUG):
        outbox = service_outbox(settings)  # down or refused at start: the service serves, and says so
    try:
        status = store_status(outbox.state())
        assert not status.reachable and status.error and "password authentication failed" in status.error
        assert wrong not in status.model_dump_json() and cluster.password not in status.model_dump_json()
        assert caplog.records and all(wrong not in r.getMessage() for r in caplog.records)
    finally:
        outbox.close(timeout_s=1)
    (tmp_path / "password").write_text(cluster.password + "\n")
    right = settings.store.model_copy(update={"password_file": tmp_path / "password"})
    store = open_store(right, tmp_path, "gcdtrav")  # the file wins over the environment
    try:
        assert store.location == url and cluster.password not in store.location
    finally:
        store.close()


def test_a_store_of_a_newer_schema_stops_the_start_in_one_line(tmp_path: Path) -> None:
    settings = ServiceSettings.model_validate({"state_dir": tmp_path})
    first = service_outbox(settings)
    assert first.store is not None
    with first.store._transaction("schema") as cursor:  # type: ignore[attr-defined]
        cursor.execute(f"UPDATE schema_version SET version = {SCHEMA_VERSION + 1}")  # as a newer gcdtrav would
    first.close()
    newer = rf"schema version {SCHEMA_VERSION + 1}, this gcdtrav knows up to {SCHEMA_VERSION}: run a newer gcdtrav"
    with pytest.raises(SchemaTooNew, match=newer):
        service_outbox(settings)


def test_a_corrupt_sqlite_file_is_an_unreachable_store_and_the_service_serves_on(tmp_path: Path) -> None:
    settings = ServiceSettings.model_validate({"state_dir": tmp_path})
    (tmp_path / "gcdtrav.store.sqlite3").write_bytes(b"not a database at all" * 100)
    outbox = service_outbox(settings)
    try:
        state = outbox.state()
        assert outbox.store is None and not state.reachable and "file is not a database" in (state.error or "")
        assert outbox.put([]) == 0  # pairs would wait in memory, as in any outage
    finally:
        outbox.close(timeout_s=1)
