"""Real components the tests run against (PostgreSQL, ROS 2's rclpy, Prometheus): skipped here, required in CI.

A developer without Debian's ``postgresql`` or the ROS 2 wheels still runs the rest of the suite; the skip says
what to install. CI names what it installed in ``GCDTRAV_REQUIRE`` (``.ci/run``), and there a missing component
fails the test instead of skipping it, so a broken install step can never pass as "skipped".
"""

from __future__ import annotations

import importlib.util
import os
import shutil
from pathlib import Path
from typing import NoReturn

import pytest

REQUIRE_ENV = "GCDTRAV_REQUIRE"


def required() -> set[str]:
    """The components CI installed and so requires: names from GCDTRAV_REQUIRE (space or comma separated)."""
    return set(os.environ.get(REQUIRE_ENV, "").replace(",", " ").split())


def missing(component: str, how_to_install: str) -> NoReturn:
    """Skip (locally) or fail (where CI requires the component) a test that needs ``component``."""
    message = f"{component} is not installed here ({how_to_install})"
    if component in required():
        pytest.fail(f"{message}, but {REQUIRE_ENV} requires it", pytrace=False)
    pytest.skip(message, allow_module_level=True)  # also from a module's top (tests/client/test_relay_ros2*.py)


def postgresql_bin() -> Path:
    """The directory of Debian's PostgreSQL server programs (initdb, pg_ctl, postgres), newest version first."""
    for version_dir in sorted(Path("/usr/lib/postgresql").glob("*/bin"), reverse=True):
        if (version_dir / "initdb").exists() and (version_dir / "pg_ctl").exists():
            return version_dir
    missing("postgresql", "apt-get install postgresql")


def require_rclpy() -> None:
    """ROS 2's own client library (the Kilted wheels on PyPI: ros-rclpy and the message packages)."""
    if importlib.util.find_spec("rclpy") is None:
        missing("rclpy", "pip install ros-rclpy ros-rmw-fastrtps-cpp and the message packages, see .ci/run")
    try:
        import rclpy  # noqa: F401
    except ImportError as err:  # wheels installed outside this venv: their libraries are not on its path
        missing("rclpy", f"it is installed but does not import: {err}")


def require_prometheus() -> str:
    """The path of a real Prometheus server (Debian's prometheus package)."""
    path = shutil.which("prometheus")
    if path is None:
        missing("prometheus", "apt-get install prometheus")
    return path


def nss_wrapper() -> Path:
    """cwrap's nss_wrapper (Debian libnss-wrapper): a test resolver loaded with LD_PRELOAD, which answers host
    names from the file NSS_WRAPPER_HOSTS, so a process resolves the cluster's names to 127.0.0.1 without
    /etc/hosts or DNS being touched."""
    for folder in ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib64", "/usr/lib"):
        if (Path(folder) / "libnss_wrapper.so").exists():
            return Path(folder) / "libnss_wrapper.so"
    missing("nss_wrapper", "apt-get install libnss-wrapper")
