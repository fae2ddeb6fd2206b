"""``store:``: where what the fleet must remember lives (experience pairs, anchor-set history, the active set;
docs/calibration.md). Absent: SQLite in the state dir, nothing to set up. A fleet names one PostgreSQL database.

The password never sits in the settings: it comes from ``password_file`` or the environment variable
``GCDTRAV_STORE_PASSWORD`` (a URL holding one is refused: it would show in logs and status)."""

from __future__ import annotations

from pathlib import Path
from urllib.parse import urlsplit

from gcdtrav.schemas.strict import StrictModel
from pydantic import Field, field_validator

PASSWORD_ENV = "GCDTRAV_STORE_PASSWORD"
POSTGRESQL_SCHEMES = ("postgresql", "postgres")


class StoreSettings(StrictModel):
    """``store:``: the database of pairs and anchor history; absent url: SQLite in the state dir."""

    url: str | None = Field(
        default=None,
        description="postgresql://USER@HOST:PORT/DATABASE of a fleet's shared store; none: SQLite in state_dir.",
    )
    password_file: Path | None = Field(
        default=None, description=f"A file holding the database password; else env {PASSWORD_ENV}; never logged."
    )
    outbox_pairs: int = Field(
        default=100_000,
        ge=1,
        description="Pairs held in memory while the store cannot be written; beyond that they are dropped, counted.",
    )
    connect_timeout_s: float = Field(
        default=5.0, gt=0, le=600, description="How long one connection attempt to the database may take."
    )
    retry_s: float = Field(
        default=2.0, gt=0, le=600, description="How often an unreachable store is tried again, at most, s."
    )
    pool_size: int = Field(
        default=3,
        ge=1,
        le=64,
        description="PostgreSQL: connections this instance holds at most (the outbox's writer, the anchor switch's "
        "reader and worker); a server needs max_connections >= instances x pool_size + its reserved ones.",
    )
    pool_wait_s: float = Field(
        default=10.0, gt=0, le=600, description="PostgreSQL: how long a call waits for a free pooled connection, s."
    )

    @field_validator("url")
    @classmethod
    def _postgresql_without_password(cls, value: str | None) -> str | None:
        if value is None:
            return None
        try:
            parts = urlsplit(value)
            _ = parts.port  # a bad port raises here
        except ValueError as err:
            raise ValueError(f"store: url is not a URL ({err})") from None
        if parts.scheme not in POSTGRESQL_SCHEMES:
            raise ValueError(
                f"store: url must start with postgresql:// (got scheme '{parts.scheme}'); leave it out for SQLite "
                "in the state dir"
            )
        if parts.password is not None:
            raise ValueError(
                f"store: url holds a password, which would show in logs and status: give it in password_file or "
                f"the environment variable {PASSWORD_ENV}"
            )
        return value
