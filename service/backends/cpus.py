"""This machine's CPUs: their name and the flags that pick kernels, and how many this process may really use
(its affinity mask, capped by a container's CPU quota).

Inside ``docker run --cpus=2`` on a 32-core host, ``os.cpu_count()`` and torch's default both say 32; torch
would start 32 threads that the kernel then throttles to the quota, stalling every frame.
"""

from __future__ import annotations

import math
import os
import platform
from pathlib import Path

CGROUP_ROOT = Path("/sys/fs/cgroup")
# The CPU flags that change which kernels torch and ONNX Runtime pick.
KERNEL_FLAGS = ("avx2", "fma", "avx512f", "avx512_vnni", "avx512_bf16", "avx_vnni", "amx_tile", "amx_int8", "amx_bf16")


def _cpuinfo_field(name: str) -> str | None:
    """The first ``name : value`` of /proc/cpuinfo (x86 Linux); None elsewhere."""
    try:
        text = Path("/proc/cpuinfo").read_text("utf-8", errors="replace")
    except OSError:
        return None
    return next((line.split(":", 1)[1].strip() for line in text.splitlines() if line.startswith(name)), None)


def cpu_name() -> str:
    return _cpuinfo_field("model name") or platform.processor() or platform.machine()


def cpu_features() -> list[str]:
    """The ``KERNEL_FLAGS`` this CPU has (empty where /proc/cpuinfo does not list flags)."""
    flags = (_cpuinfo_field("flags") or "").split()
    return sorted(flag for flag in flags if flag in KERNEL_FLAGS)


# Linux x86-64 hands a process AMX's tile registers only on request, and only if the kernel (5.16 on) and, in a
# VM, the hypervisor pass the tile state through: arch_prctl(ARCH_GET_XCOMP_SUPP) lists the state components
# the kernel offers; XTILEDATA is component 18. Without it the amx_* flags are there and no AMX kernel can run.
SYS_ARCH_PRCTL, ARCH_GET_XCOMP_SUPP, XFEATURE_XTILEDATA = 158, 0x1021, 18


def amx_tiles_offered(flags: list[str], supported: int | None) -> bool | None:
    """Whether the kernel offers AMX's tile state: None when the CPU has no AMX (its ``flags``, as
    ``cpu_features`` lists them), True or False when it has. ``supported``: the kernel's mask of state
    components (``xcomp_supported``)."""
    if "amx_tile" not in flags:
        return None
    return supported is not None and bool(supported >> XFEATURE_XTILEDATA & 1)


def xcomp_supported() -> int | None:
    """The kernel's mask of the extended state components it offers a process; None where it cannot be asked
    (not Linux x86-64, or a kernel before 5.16)."""
    if platform.system() != "Linux" or platform.machine() != "x86_64":
        return None
    import ctypes

    mask = ctypes.c_uint64(0)
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.syscall(SYS_ARCH_PRCTL, ARCH_GET_XCOMP_SUPP, ctypes.byref(mask)) != 0:
        return None  # EINVAL: a kernel that does not manage extended state components per process
    return int(mask.value)


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


def set_torch_threads(configured: int | None = None) -> int:
    """torch's intra-op threads: as configured, else torch's default capped by the usable CPUs. Every command
    that runs the model sets them the same way: the measurement of precision auto is keyed by them, so
    `gcdtrav doctor`, `infer` and `serve` find each other's figures."""
    import torch

    threads = configured if configured is not None else min(torch.get_num_threads(), usable_cpus())
    if threads != torch.get_num_threads():
        torch.set_num_threads(threads)
    return threads
