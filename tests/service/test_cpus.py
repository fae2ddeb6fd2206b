"""CPU budget: affinity capped by a container's quota (cgroup v2 and v1 files faked in a temp dir)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.backends.cpus import cpu_quota, usable_cpus


def write(root: Path, relative: str, text: str) -> None:
    path = root / relative
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text + "\n")


@pytest.mark.parametrize(
    ("files", "quota"),
    [
        ({"cpu.max": "200000 100000"}, 2.0),
        ({"cpu.max": "150000 100000"}, 1.5),
        ({"cpu.max": "max 100000"}, None),
        ({"cpu/cpu.cfs_quota_us": "300000", "cpu/cpu.cfs_period_us": "100000"}, 3.0),
        ({"cpu/cpu.cfs_quota_us": "-1", "cpu/cpu.cfs_period_us": "100000"}, None),
        ({"cpu.max": "garbage"}, None),
        ({}, None),
    ],
)
def test_cpu_quota(tmp_path: Path, files: dict[str, str], quota: float | None) -> None:
    for relative, text in files.items():
        write(tmp_path, relative, text)
    assert cpu_quota(tmp_path) == quota


def test_usable_cpus_is_the_affinity_capped_by_the_quota_rounded_down(tmp_path: Path) -> None:
    affinity = len(os.sched_getaffinity(0))
    assert usable_cpus(tmp_path) == affinity  # no quota files: no cap
    write(tmp_path, "cpu.max", "50000 100000")  # half a CPU still gets one thread
    assert usable_cpus(tmp_path) == 1
    write(tmp_path, "cpu.max", f"{(affinity + 4) * 100000} 100000")  # a quota above the mask changes nothing
    assert usable_cpus(tmp_path) == affinity
    if affinity >= 2:
        write(tmp_path, "cpu.max", "150000 100000")
        assert usable_cpus(tmp_path) == 1


def test_service_threads_default_to_the_usable_cpus(tmp_path: Path) -> None:
    torch = pytest.importorskip("torch")
    from gcdtrav.service.commands.serve import with_torch_threads

    settings = with_torch_threads(ServiceSettings(state_dir=tmp_path))
    assert settings.threads == min(torch.get_num_threads(), usable_cpus())
    assert with_torch_threads(ServiceSettings(state_dir=tmp_path, threads=3)).threads == 3
