"""The torch-free operator commands against a real service on loopback: status, anchors get/set."""

from __future__ import annotations

import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import textured_image, torch_free_gcdtrav
from zenoh_helpers import connecting_config, first_frame_through, service_reachable, wait_until

pytest.importorskip("torch")

from gcdtrav.client import TraversabilityClient
from gcdtrav.client.commands.operator import anchor_diff
from gcdtrav.schemas.anchors import AnchorSet, default_anchor_set
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.bus.node import TraversabilityService

from tools.loopback import in_process_service

ROOT = Path(__file__).resolve().parents[2]
PUDDLES = ROOT / "examples" / "anchors" / "puddles.yaml"


def gcdtrav(*args: str) -> subprocess.CompletedProcess[str]:
    """`gcdtrav ARGS` in a fresh interpreter where torch and transformers cannot be imported."""
    return subprocess.run(torch_free_gcdtrav(*args), capture_output=True, text=True, timeout=60)


@pytest.fixture()
def service(tiny_backend, tmp_path: Path) -> Iterator[tuple[TraversabilityService, list[str]]]:  # type: ignore[no-untyped-def]
    settings = ServiceSettings(state_dir=tmp_path / "state", instance="ops-1", preview=False)
    with in_process_service(tiny_backend, settings) as (running, port):
        with TraversabilityClient(config=connecting_config(port), timeout=5.0) as client:
            first_frame_through(client, "r1/front", textured_image(48, 64))
        yield running, ["-m", "client", "-e", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"]


def test_status_anchors_get_and_a_swap_with_its_diff(service, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    running, flags = service
    status = gcdtrav("status", *flags)
    assert status.returncode == 0, status.stderr
    assert "ops-1" in status.stdout and "r1/front" in status.stdout and "tiny" not in status.stderr
    row = next(line for line in status.stdout.splitlines() if line.startswith("r1/front"))
    assert row.split()[1:6] == ["ops-1", "-", "1", "1", "0"]  # instance, frames/s, received, processed, dropped
    instance_row = next(line for line in status.stdout.splitlines() if line.startswith("ops-1"))
    assert f"/ {running.pipeline.anchors.version} / gcd / fp32 " in instance_row  # anchors, method, precision
    assert "precision ops-1: fp32 (asked for fp32)" in status.stdout  # and why that mode runs

    shown = gcdtrav("anchors", "get", *flags)
    assert shown.returncode == 0 and f"# active anchor set {default_anchor_set().version}" in shown.stdout
    saved = tmp_path / "active.yaml"
    assert gcdtrav("anchors", "get", "-o", str(saved), *flags).returncode == 0
    assert AnchorSet.load(saved) == running.pipeline.anchors

    dry = gcdtrav("anchors", "set", str(PUDDLES), "--dry-run", *flags)
    new = AnchorSet.load(PUDDLES)
    assert dry.returncode == 0, dry.stderr
    assert dry.stdout.splitlines()[0] == f"{default_anchor_set().version} (13 anchors) -> {new.version} (8 anchors)"
    assert "\n".join(anchor_diff(default_anchor_set(), new)) in dry.stdout and "dry run: nothing swapped" in dry.stdout
    assert running.pipeline.anchors.version == default_anchor_set().version  # nothing swapped

    swap = gcdtrav("anchors", "set", str(PUDDLES), *flags)
    assert swap.returncode == 0, swap.stderr
    assert f"swapped: anchor set {new.version} active on ops-1 ({new.version})" in swap.stdout
    assert running.pipeline.anchors.version == new.version


def test_probe_prints_a_pixels_distribution_and_draws_it(service, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    running, flags = service
    png = tmp_path / "probe.png"
    probe = gcdtrav("probe", "r1/front", "20", "10", "--png", str(png), *flags)
    assert probe.returncode == 0, probe.stderr
    from gcdtrav.service.runtime.queries import answer_patch_query

    expected = answer_patch_query(running.runtime.history, "r1/front", {"x": "20", "y": "10"})
    assert expected.patch is not None
    i, j = expected.patch  # the answer in the user's terms: the pixel as typed (x, y), the patch named (row, column)
    assert probe.stdout.startswith(f"r1/front pixel (x=20, y=10) in seq={expected.seq} patch (row i={i}, column j={j})")
    assert "T (mean) =" in probe.stdout and "concrete @ 1.00" in probe.stdout
    assert (
        f"CVaR(alpha=0.1) = {expected.cvar:.3f}" in probe.stdout
        and f"P(T < 0.3) = {expected.p_below:.3f}" in probe.stdout
    )
    tighter = gcdtrav("probe", "r1/front", "20", "10", "--alpha", "0.5", "--tau", "0.9", *flags)
    assert "CVaR(alpha=0.5)" in tighter.stdout and "P(T < 0.9)" in tighter.stdout
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    outside = gcdtrav("probe", "r1/front", "5000", "10", *flags)
    assert outside.returncode == 1 and "outside the 64x48 image" in outside.stderr


def test_history_and_rollback_survive_a_restart(tiny_backend, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    settings = ServiceSettings(state_dir=tmp_path / "state", instance="ops-2", preview=False)
    puddles = AnchorSet.load(PUDDLES)
    two = {"name": "two", "anchors": [{"concept": "lake", "position": 0.0}, {"concept": "road", "position": 1.0}]}
    with in_process_service(tiny_backend, settings) as (running, port):
        flags = ["-m", "client", "-e", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"]
        with TraversabilityClient(config=connecting_config(port), timeout=5.0) as client:
            assert wait_until(lambda: service_reachable(client), 30)
            client.set_anchors(puddles)
            client.set_anchors(two)
        history = gcdtrav("anchors", "history", *flags)
        assert history.returncode == 0, history.stderr
        lines = history.stdout.splitlines()
        assert lines[0] == "instance ops-2:" and len(lines) == 4
        assert "active" in lines[1] and "two" in lines[1] and "rollback 1" in lines[2] and puddles.version in lines[2]
        assert default_anchor_set().version in lines[3]  # the set it started with
        rolled = gcdtrav("anchors", "rollback", *flags)
        assert rolled.returncode == 0, rolled.stderr
        assert f"rolled back: anchor set {puddles.version} active on ops-2 ({puddles.version})" in rolled.stdout
        assert "- lake @ 0.00" in rolled.stdout and running.pipeline.anchors.version == puddles.version
        too_far = gcdtrav("anchors", "rollback", "9", *flags)
        assert too_far.returncode == 1 and "no set 9 step(s) back" in too_far.stderr
    # A restarted service serves the store's active set and history (SQLite in the state directory), whatever
    # set it is started with: the configured one seeds an empty store only.
    with in_process_service(tiny_backend, settings) as (running, port):
        assert running.pipeline.anchors.version == puddles.version
        entries = running.runtime.anchor_switch.history().entries
        assert [(e.version, e.how) for e in entries] == [
            (puddles.version, "rollback"),
            (AnchorSet.parse(two).version, "set"),
            (puddles.version, "set"),
            (default_anchor_set().version, "seeded"),
        ]


def test_failures_are_one_line_with_the_right_exit_code(service, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    running, flags = service
    bad = tmp_path / "bad.yaml"
    bad.write_text("anchors:\n  - {concept: mud, position: 1.5}\n")
    rejected = gcdtrav("anchors", "set", str(bad), *flags)
    assert rejected.returncode == 2 and len(rejected.stderr.strip().splitlines()) == 1  # a usage error (README)
    assert "position 1.5 is outside [0, 1]" in rejected.stderr
    assert running.pipeline.anchors.version == default_anchor_set().version
    missing = gcdtrav("anchors", "set", str(tmp_path / "nope.yaml"), *flags)
    assert missing.returncode == 2 and "cannot read the file" in missing.stderr
    unreachable = gcdtrav("status", "-m", "client", "-e", "tcp/127.0.0.1:9", "--no-multicast-scouting")
    assert unreachable.returncode == 1 and len(unreachable.stderr.strip().splitlines()) == 1
    assert unreachable.stderr.startswith("gcdtrav status: zenoh: Unable to connect to any of [")
    assert "tcp/127.0.0.1:9" in unreachable.stderr and ".rs:" not in unreachable.stderr
    usage = gcdtrav("anchors", "swap", "x.yaml")
    assert usage.returncode == 2
    for args in (("answer", "cam", "1.5"), ("answer", "cam", "maybe"), ("anchors", "rollback", "0")):
        usage = gcdtrav(*args, *flags)
        assert usage.returncode == 2 and "Traceback" not in usage.stderr, (args, usage.stderr)
    assert "a score must be in [0, 1]" in gcdtrav("answer", "cam", "1.5", *flags).stderr


def test_diff_names_added_removed_and_moved_concepts() -> None:
    active = AnchorSet.parse({"anchors": [{"concept": "mud", "position": 0.1}, {"concept": "road", "position": 1.0}]})
    new = AnchorSet.parse(
        {
            "name": "x",
            "anchors": [{"concept": "mud", "position": 0.2, "width": 0.05}, {"concept": "grass", "position": 0.7}],
        }
    )
    assert anchor_diff(active, new) == [
        "- road @ 1.00",
        "~ mud @ 0.10 -> 0.20, width 0 -> 0.05",
        "+ grass @ 0.70",
        "~ name 'custom' -> 'x'",
    ]
