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


@pytest.mark.parametrize(
    ("flags", "supported", "offered"),
    [
        (["avx512f"], 0b111 | 1 << 18, None),  # no AMX: nothing to offer, whatever the kernel says
        (["amx_tile", "amx_bf16"], 0b11100111 | 0b11 << 17, True),  # tile config and data (17, 18)
        (["amx_tile", "amx_bf16"], 0b11100111, False),  # a VM that keeps the tile state to itself
        (["amx_tile"], None, False),  # a kernel that cannot be asked (before 5.16)
    ],
)
def test_amx_tiles_are_usable_only_where_the_kernel_offers_their_state(
    flags: list[str], supported: int | None, offered: bool | None
) -> None:
    from gcdtrav.service.backends.cpus import amx_tiles_offered

    assert amx_tiles_offered(flags, supported) is offered


def test_this_kernel_answers_which_state_it_offers() -> None:
    """The real arch_prctl: a mask with x87 and SSE at least on Linux x86-64, None elsewhere."""
    import platform

    from gcdtrav.service.backends.cpus import xcomp_supported

    mask = xcomp_supported()
    if platform.system() == "Linux" and platform.machine() == "x86_64" and mask is not None:
        assert mask & 0b11 == 0b11  # every x86-64 kernel manages x87 and SSE state
    elif platform.system() != "Linux" or platform.machine() != "x86_64":
        assert mask is None


def test_doctor_says_whether_amx_tiles_are_offered(monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("torch")
    from gcdtrav.service.backends.cpus import XFEATURE_XTILEDATA, cpu_features, xcomp_supported
    from gcdtrav.service.commands import doctor

    mask, has_amx = xcomp_supported(), "amx_tile" in cpu_features()  # this machine's own answer first
    expected = (mask is not None and bool(mask >> XFEATURE_XTILEDATA & 1)) if has_amx else None
    assert doctor.machine_info()["amx_tiles"] is expected
    for offered, says in ((None, None), (True, "offered by the kernel"), (False, "NOT offered by the kernel")):
        monkeypatch.setattr(doctor, "amx_tiles_offered", lambda flags, supported, offered=offered: offered)
        lines = [line for line in doctor.machine_lines() if line.startswith("AMX tiles")]
        assert lines == ([] if says is None else [f"AMX tiles    {doctor.AMX_TILES[offered]}"])
        if says:
            assert says in lines[0]
