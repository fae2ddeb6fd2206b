"""A throw-away PostgreSQL cluster for tests: initdb in a temporary folder, the server on a free loopback port
with its unix socket in that folder, password authentication over TCP, torn down afterwards.

Debian's server programs come from ``real_components.postgresql_bin()`` (skipped locally without them, a
failure in CI). PostgreSQL refuses to run as root, and CI runs as root: then every server program runs as the
``postgres`` user (``runuser``), which owns the folder."""

from __future__ import annotations

import contextlib
import importlib.util
import os
import pwd
import secrets
import shutil
import socket
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from real_components import missing, postgresql_bin

SUPERUSER = "gcdtrav"


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


class PostgresCluster:
    """One server; ``stop`` and ``start`` keep its data and port (an outage), ``destroy`` removes it all."""

    def __init__(self, bin_dir: Path, durable: bool = False, max_connections: int = 60) -> None:
        """``durable``: fsync as a production server does (benchmarks); off in tests, which never crash it."""
        self.bin_dir, self.durable, self.max_connections = bin_dir, durable, max_connections
        self.root = Path(tempfile.mkdtemp(prefix="gcdtrav-pg-"))
        self.data, self.sockets, self.log = self.root / "data", self.root / "sockets", self.root / "server.log"
        self.port = free_port()
        self.password = secrets.token_urlsafe(16)
        self.as_user = self._server_user()
        self.sockets.mkdir()
        password_file = self.root / "password"
        password_file.write_text(self.password + "\n")
        if self.as_user is not None:
            entry = pwd.getpwnam(self.as_user)
            for path in (self.root, self.sockets, password_file):
                os.chown(path, entry.pw_uid, entry.pw_gid)
        self._run("initdb", "-D", str(self.data), "-U", SUPERUSER, f"--pwfile={password_file}",
                  "--auth-local=trust", "--auth-host=scram-sha-256", "--no-sync", "-E", "UTF8")  # fmt: skip
        password_file.unlink()

    @staticmethod
    def _server_user() -> str | None:
        if os.geteuid() != 0:
            return None
        try:
            pwd.getpwnam("postgres")
        except KeyError:
            pytest.fail("running as root, PostgreSQL needs the 'postgres' user (Debian's postgresql package makes it)")
        return "postgres"

    def _run(self, program: str, *args: str) -> None:
        command = [str(self.bin_dir / program), *args]
        if self.as_user is not None:
            command = ["runuser", "-u", self.as_user, "--", *command]
        result = subprocess.run(command, capture_output=True, text=True, timeout=120, check=False)
        if result.returncode != 0:
            log = self.log.read_text(errors="replace")[-2000:] if self.log.exists() else ""
            raise RuntimeError(f"{program} failed ({result.returncode}): {result.stderr.strip()}\n{log}")

    def start(self) -> None:
        fsync = "on" if self.durable else "off"
        options = (f"-c listen_addresses=127.0.0.1 -p {self.port} -k {self.sockets} -c fsync={fsync} "
                   f"-c max_connections={self.max_connections} -c superuser_reserved_connections=0")  # fmt: skip
        self._run("pg_ctl", "-D", str(self.data), "-l", str(self.log), "-w", "-t", "60", "-o", options, "start")

    def stop(self) -> None:
        """A fast shutdown: open connections are cut, as when a database pod goes away."""
        self._run("pg_ctl", "-D", str(self.data), "-m", "fast", "-w", "-t", "60", "stop")

    def url(self, database: str = "postgres") -> str:
        return f"postgresql://{SUPERUSER}@127.0.0.1:{self.port}/{database}"

    def create_database(self, name: str) -> str:
        """A fresh database; its URL (no password: give ``password`` apart)."""
        import psycopg

        with psycopg.connect(self.url(), password=self.password, autocommit=True) as connection:
            connection.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def destroy(self) -> None:
        with contextlib.suppress(RuntimeError):
            self.stop()
        shutil.rmtree(self.root, ignore_errors=True)


@contextlib.contextmanager
def postgres_cluster(durable: bool = False, max_connections: int = 60) -> Iterator[PostgresCluster]:
    if importlib.util.find_spec("psycopg") is None:
        missing("postgresql", "psycopg: pip install 'gcdtrav[service]'")
    cluster = PostgresCluster(postgresql_bin(), durable, max_connections)
    try:
        cluster.start()
        yield cluster
    finally:
        cluster.destroy()
