"""How many CPUs this process may really use: its affinity mask, capped by a container's CPU quota.

Inside ``docker run --cpus=2`` on a 32-core host, ``os.cpu_count()`` and torch's default both say 32; torch
would start 32 threads that the kernel then throttles to the quota, stalling every frame.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

CGROUP_ROOT = Path("/sys/fs/cgroup")


def _read(path: Path) -> str | None:
    try:
        return path.read_text("utf-8").strip()
    except OSError:
        return None


def cpu_quota(root: Path = CGROUP_ROOT) -> float | None:
    """CPUs' worth of time the cgroup may use per period (cgroup v2 ``cpu.max`` or v1 CFS), None if unlimited."""
    v2 = _read(root / "cpu.max")  # "max 100000" or "200000 100000"
    if v2 is not None:
        quota, _, period = v2.partition(" ")
        if quota != "max" and quota.isdigit() and period.isdigit() and int(period) > 0:
            return int(quota) / int(period)
        return None
    quota_v1, period_v1 = _read(root / "cpu" / "cpu.cfs_quota_us"), _read(root / "cpu" / "cpu.cfs_period_us")
    if quota_v1 and period_v1 and quota_v1.lstrip("-").isdigit() and period_v1.isdigit():
        quota_us, period_us = int(quota_v1), int(period_v1)
        if quota_us > 0 and period_us > 0:
            return quota_us / period_us
    return None


def usable_cpus(root: Path = CGROUP_ROOT) -> int:
    """CPUs in this process's affinity mask, capped by the CPU quota (rounded down: a throttled thread stalls)."""
    affinity = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    quota = cpu_quota(root)
    if quota is None:
        return affinity
    return max(1, min(affinity, math.floor(quota)))
