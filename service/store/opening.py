"""Opening the store the settings name: SQLite in the state dir (no ``store.url``), else PostgreSQL with the
password from ``password_file`` or GCDTRAV_STORE_PASSWORD (never from the settings, never shown)."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

from gcdtrav.schemas.settings.service import ServiceSettings
from gcdtrav.schemas.settings.store import PASSWORD_ENV, StoreSettings
from gcdtrav.service.store import legacy
from gcdtrav.service.store.base import Store
from gcdtrav.service.store.outbox import PairOutbox
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

    return PostgresStore(
        settings.url, store_password(settings), settings.connect_timeout_s, settings.pool_size, settings.pool_wait_s
    )


def location_of(settings: StoreSettings, state_dir: Path, prefix: str) -> tuple[str, str]:
    """(backend, location) before the store is open: for logs and status while it cannot be reached."""
    if settings.url is None:
        return "sqlite", str(sqlite_file(state_dir, prefix))
    return "postgresql", settings.url


def import_legacy_files(store: Store, settings: ServiceSettings) -> None:
    """The files of a gcdtrav before the store, imported once (service/store/legacy.py) and renamed (the store is
    their record): the msgpack pairs (as pairs of the experience's grid) and the anchor state with its history
    (only into a store without an active set)."""
    grid = settings.experience.grid or (settings.grids[0].source if settings.grids else "")
    legacy.import_experience_file(store, legacy.experience_file(settings.state_dir, settings.prefix), grid,
                                  settings.instance)  # fmt: skip
    legacy.import_anchor_state(store, settings.state_file, settings.instance)


def service_store(settings: ServiceSettings, opened: Store | None = None) -> Store:
    """The service's store (``opened``, or the one the settings name), with a gcdtrav's files from before the store
    imported into it at its first open: `gcdtrav serve` opens it once at start, the outbox again only until it
    answers. StoreUnavailable while it cannot be reached; another StoreError if it is refused."""
    store = opened or open_store(settings.store, settings.state_dir, settings.prefix)
    try:
        import_legacy_files(store, settings)
    except BaseException:
        store.close()
        raise
    return store


def service_outbox(settings: ServiceSettings, opened: Store | None = None) -> PairOutbox:
    """The service's way to its store, opened now if it can be (the old files imported at the first open);
    else the outbox's writer keeps trying and the service serves meanwhile. StoreError (SchemaTooNew, a bad
    password_file, psycopg missing) if the store is refused: the service does not start. ``opened``: a store
    opened by the caller (tests: instances sharing one SQLite file) instead of the one the settings name."""
    backend, location = location_of(settings.store, settings.state_dir, settings.prefix)
    if opened is not None:
        backend, location = opened.backend, opened.location

    def opener() -> Store:
        return service_store(settings, opened)

    age_days = settings.experience.max_age_days
    outbox = PairOutbox(opener, backend, location, settings.store.outbox_pairs, settings.experience.max_pairs,
                        settings.experience.max_bytes, settings.store.retry_s,
                        max_age_s=None if age_days is None else age_days * 86_400.0,
                        sample_size=settings.experience.sample_per_source)  # fmt: skip
    outbox.open_now()
    return outbox
