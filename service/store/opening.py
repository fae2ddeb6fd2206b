"""Opening the store the settings name: SQLite in the state dir (no ``store.url``), else PostgreSQL with the
password from ``password_file`` or GCDTRAV_STORE_PASSWORD (never from the settings, never shown)."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

from gcdtrav.schemas.settings.store import PASSWORD_ENV, StoreSettings
from gcdtrav.service.store.base import Store
from gcdtrav.service.store.records import StoreError


def sqlite_file(state_dir: Path, prefix: str) -> Path:
    """Named by prefix, as the anchor state: a restarted process must find it."""
    return state_dir / f"{prefix.replace('/', '_')}.store.sqlite3"


def store_password(settings: StoreSettings, environ: Mapping[str, str] | None = None) -> str | None:
    """The password from ``password_file`` (its first line), else the environment; None: none given (peer or
    trust authentication). A StoreError names the file, never its content."""
    if settings.password_file is not None:
        try:
            text = settings.password_file.read_text("utf-8")
        except OSError as err:
            raise StoreError(f"store: cannot read password_file {settings.password_file}: {err.strerror}") from None
        return text.splitlines()[0] if text else ""
    env = os.environ if environ is None else environ
    return env.get(PASSWORD_ENV)


def open_store(settings: StoreSettings, state_dir: Path, prefix: str) -> Store:
    """The store the settings name, schema created or migrated forward; SchemaTooNew for a newer store,
    StoreUnavailable when PostgreSQL cannot be reached (the caller decides whether to wait)."""
    if settings.url is None:
        from gcdtrav.service.store.sqlite import SqliteStore

        return SqliteStore(sqlite_file(state_dir, prefix))
    from gcdtrav.service.store.postgres import PostgresStore

    return PostgresStore(settings.url, store_password(settings), settings.connect_timeout_s)
