"""Issue 46's anchor criteria end to end: two instances sharing one store (one SQLite file opened by each, or
one database of a throw-away PostgreSQL cluster), a zenoh router on loopback and the operator's `gcdtrav`
(torch-free subprocesses):
- two concurrent `gcdtrav anchors set` against the fleet: exactly one wins, the other exits 1 in one line
  naming the winner, and the fleet serves the winner;
- a set applied before a full restart (every instance stopped, new ones on empty state dirs) is active after;
- `gcdtrav anchors apply VERSION` applies exactly the kept proposal, refuses a gone one, one judged against
  a set no longer active, and a worse one without --force; a forced one is marked in the history."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import zenoh
from store_test_helpers import proposal_of
from zenoh_helpers import client_config, free_port, start_router, wait_until

pytest.importorskip("torch")

from conftest import three_anchor_set
from gcdtrav.client import QueryTimeout, TraversabilityClient
from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.schemas.config import EngineSettings
from gcdtrav.schemas.experience import ProposalVerdict
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.bus.node import TraversabilityService
from gcdtrav.service.pipeline import Pipeline
from store_fixtures import OpenStore


class SharedStoreFleet:
    """Instances on one router, each on its own empty state dir, all on one store."""

    def __init__(self, backend: Any, port: int, root: Path, open_store: OpenStore) -> None:
        self.backend, self.port, self.root, self.open_store = backend, port, root, open_store
        self.running: dict[str, tuple[TraversabilityService, zenoh.Session]] = {}

    def start(self, instance: str) -> TraversabilityService:
        session = zenoh.open(client_config(self.port))
        settings = ServiceSettings(state_dir=self.root / instance, instance=instance, preview=False)
        pipeline = Pipeline(self.backend, default_anchor_set(), EngineSettings())  # the ConfigMap's set
        service = TraversabilityService(session, pipeline, settings, store=self.open_store())
        service.start()
        self.running[instance] = (service, session)
        return service

    def versions(self) -> dict[str, str]:
        return {name: service.pipeline.anchors.version for name, (service, _) in self.running.items()}

    def converged_on(self, version: str) -> bool:
        return set(self.versions().values()) == {version}

    def stop(self) -> None:
        for service, session in self.running.values():
            service.stop()
            session.close()
        self.running.clear()


def answering(client: TraversabilityClient) -> int:
    """How many instances answer a status query (none yet, while the router has not told the client of any
    queryable: statuses raises QueryTimeout at once then)."""
    try:
        return len(client.statuses(timeout=5.0))
    except QueryTimeout:
        return 0


@contextmanager
def fleet_on_one_store(
    backend: Any, root: Path, open_store: OpenStore, *instances: str
) -> Iterator[tuple[SharedStoreFleet, TraversabilityClient, list[str]]]:
    port = free_port()
    router = start_router(port)
    fleet = SharedStoreFleet(backend, port, root, open_store)
    client = TraversabilityClient(config=client_config(port), timeout=5.0)
    try:
        for name in instances:
            fleet.start(name)
        assert wait_until(lambda: answering(client) == len(instances), 60)
        yield fleet, client, ["-m", "client", "-e", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"]
    finally:
        client.close()
        fleet.stop()
        router.terminate()
        router.communicate(timeout=20)


def torch_free_gcdtrav(*args: str) -> list[str]:
    """`gcdtrav ARGS` where torch cannot be imported (tests/conftest.py's, which this folder's conftest hides)."""
    main = f"from gcdtrav.service.commands.cli import main; sys.exit(main({list(args)!r}))"
    code = f"import sys; sys.modules['torch'] = None; {main}"
    return [sys.executable, "-c", code]


def gcdtrav(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(torch_free_gcdtrav(*args), capture_output=True, text=True, timeout=60)


def test_two_operators_setting_at_once_exactly_one_wins_the_other_exits_1_naming_it(
    tiny_backend: Any, tmp_path: Path, open_same_store: OpenStore
) -> None:
    with fleet_on_one_store(tiny_backend, tmp_path, open_same_store, "box-a", "box-b") as (fleet, client, flags):
        seen = client.anchors().version  # both operators reviewed their change against this set
        files = {}
        for name in ("left", "right"):
            files[name] = tmp_path / f"{name}.yaml"
            three_anchor_set(name).save(files[name])
        operators = {
            name: subprocess.Popen(
                torch_free_gcdtrav("anchors", "set", str(path), "--expected", seen, *flags),
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
            for name, path in files.items()
        }
        done = {name: (process.wait(60), *process.communicate()) for name, process in operators.items()}
        assert sorted(code for code, _, _ in done.values()) == [0, 1], done
        winner = next(name for name, (code, _, _) in done.items() if code == 0)
        loser = next(name for name in done if name != winner)
        version = three_anchor_set(winner).version
        assert f"swapped: anchor set {version} active on" in done[winner][1]
        refusal = done[loser][2].splitlines()
        assert len(refusal) == 1 and refusal[0].startswith(f"gcdtrav anchors: lost to anchor set {version}: ")
        assert f"expected {seen} to be active: nothing swapped" in refusal[0]
        assert wait_until(lambda: fleet.converged_on(version), 60), fleet.versions()
        store = fleet.running["box-a"][0].runtime.anchor_switch.store
        assert [(entry.version, entry.how) for entry in store.history(5)] == [(version, "set"), (seen, "seeded")]


def test_a_set_applied_before_a_full_restart_is_active_after_it(
    tiny_backend: Any, tmp_path: Path, open_same_store: OpenStore
) -> None:
    applied = three_anchor_set("applied")
    with fleet_on_one_store(tiny_backend, tmp_path / "before", open_same_store, "box-a", "box-b") as (
        fleet,
        client,
        _,
    ):
        assert client.set_anchors(applied, expected_version=client.anchors().version) == applied.version
        assert fleet.converged_on(applied.version)
    # every instance stopped; new ones on empty state dirs, the same store, the ConfigMap's set configured
    with fleet_on_one_store(tiny_backend, tmp_path / "after", open_same_store, "box-c", "box-d") as (
        fleet,
        client,
        flags,
    ):
        assert fleet.versions() == {"box-c": applied.version, "box-d": applied.version}
        history = gcdtrav("anchors", "history", *flags)
        assert history.returncode == 0, history.stderr
        lines = history.stdout.splitlines()
        assert lines[0] == "instance box-c, box-d:" and len(lines) == 3  # one shared history, shown once
        assert applied.version in lines[1] and "set by box-" in lines[1] and "seeded" in lines[2]


def test_apply_by_version_applies_exactly_the_kept_proposal_or_refuses_in_one_line(
    tiny_backend: Any, tmp_path: Path, open_same_store: OpenStore
) -> None:
    better = ProposalVerdict(verdict="better", figures=[], held_out_pairs=500, enough_pairs=True)
    worse = better.model_copy(update={"verdict": "worse"})
    with fleet_on_one_store(tiny_backend, tmp_path, open_same_store, "box-a", "box-b") as (fleet, _, flags):
        store = fleet.running["box-a"][0].runtime.anchor_switch.store
        start = default_anchor_set()
        reviewed, stale, forced = three_anchor_set("reviewed"), three_anchor_set("stale"), three_anchor_set("forced")
        store.put_proposal(proposal_of(start, reviewed).model_copy(update={"verdict": better, "kept": True}), "box-b")
        store.put_proposal(proposal_of(start, stale).model_copy(update={"verdict": better, "kept": True}), "box-b")

        gone = gcdtrav("anchors", "apply", "0123456789abcdef", *flags)
        assert gone.returncode == 1 and len(gone.stderr.splitlines()) == 1
        assert "no kept proposal 0123456789abcdef: it is gone" in gone.stderr

        applied = gcdtrav("anchors", "apply", reviewed.version, *flags)
        assert applied.returncode == 0, applied.stderr
        assert wait_until(lambda: fleet.converged_on(reviewed.version), 60), fleet.versions()
        assert fleet.running["box-b"][0].pipeline.anchors == reviewed  # exactly the kept set

        # judged against the start set, which is no longer active: refused, naming the set that is
        late = gcdtrav("anchors", "apply", stale.version, *flags)
        assert late.returncode == 1 and len(late.stderr.splitlines()) == 1
        assert f"lost to anchor set {reviewed.version}" in late.stderr

        store.put_proposal(proposal_of(reviewed, forced).model_copy(update={"verdict": worse, "kept": True}), "box-a")
        refused = gcdtrav("anchors", "apply", forced.version, *flags)
        assert refused.returncode == 1 and "is not applied: worse on the held-out pairs" in refused.stderr
        assert fleet.converged_on(reviewed.version)
        forcing = gcdtrav("anchors", "apply", forced.version, "--force", *flags)
        assert forcing.returncode == 0, forcing.stderr
        assert wait_until(lambda: fleet.converged_on(forced.version), 60), fleet.versions()
        history = gcdtrav("anchors", "history", *flags).stdout.splitlines()
        assert forced.version in history[1] and history[1].endswith("FORCED (against its verdict)")
        assert reviewed.version in history[2] and "proposal by box-" in history[2] and "FORCED" not in history[2]
