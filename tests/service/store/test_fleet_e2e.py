"""The fleet's pairs survive the fleet (issue 46, "Done when"): two `gcdtrav serve` instances share one real
PostgreSQL on loopback while the simulated robot of examples/experience_drive.py drives; SIGTERM the owner,
start an instance on an empty state dir, then restart every instance on empty state dirs: the fleet's pair
count never drops, and the calibration is the same whichever instance answers."""

from __future__ import annotations

import os
import signal
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from gcdtrav.client import QueryTimeout, TraversabilityClient
from gcdtrav.schemas.experience import CalibrationReport
from gcdtrav.schemas.messages import ServiceStatus
from postgres_cluster import PostgresCluster, postgres_cluster
from zenoh_helpers import client_config, free_port, serve_args, start_router, wait_until

from tools.robot_drive import CAMERA_SOURCE, BusRobot
from tools.synthetic_scene import make_world

pytest.importorskip("torch")

ROOT = Path(__file__).resolve().parents[3]
SETTINGS = ROOT / "examples" / "experience_drive.yaml"
DRIVE_S = 6.0  # simulated seconds per leg: tens of seconds of driving in all


class Fleet:
    """`gcdtrav serve` processes on one router and one database, each on a fresh, empty state dir."""

    def __init__(self, model: Path, router_port: int, database: PostgresCluster, url: str, root: Path) -> None:
        self.model, self.router_port, self.root = model, router_port, root
        self.env = {**os.environ, "GCDTRAV_STORE__URL": url, "GCDTRAV_STORE_PASSWORD": database.password}
        self.processes: dict[str, subprocess.Popen[str]] = {}

    def start(self, instance: str) -> None:
        state = self.root / instance
        state.mkdir()
        log = open(self.root / f"{instance}.log", "w")  # noqa: SIM115 - the process writes it until it ends
        router = f"tcp/127.0.0.1:{self.router_port}"
        args = serve_args(self.model, "--settings", str(SETTINGS), "-m", "client", "-e", router,
                          "--instance", instance, "--state-dir", str(state))  # fmt: skip
        self.processes[instance] = subprocess.Popen(args, stdout=log, stderr=subprocess.STDOUT, text=True, env=self.env)

    def stop(self, instance: str) -> None:
        """SIGTERM, as Kubernetes stops a pod: the service finishes, writes its queued pairs, exits 0."""
        process = self.processes.pop(instance)
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=60) == 0, (self.root / f"{instance}.log").read_text()[-3000:]

    def close(self) -> None:
        for process in self.processes.values():
            process.kill()
            process.wait(timeout=30)


def statuses(client: TraversabilityClient) -> dict[str, ServiceStatus]:
    try:
        return {s.instance: s for s in client.statuses(timeout=2.0)}
    except QueryTimeout:
        return {}


def settled_pairs(client: TraversabilityClient, instances: set[str]) -> int:
    """The fleet's pair count once every instance's queued pairs are written: what each instance reads."""

    counts: set[int] = set()

    def settled() -> bool:
        seen = statuses(client)
        counts.clear()
        counts.update(s.experience.pairs for s in seen.values() if s.experience is not None)
        return (
            set(seen) == instances
            and all(s.store is not None and s.store.reachable and s.store.pending_pairs == 0 for s in seen.values())
            and len(counts) == 1  # one store: every instance counts the same pairs (each reads it every second)
        )

    assert wait_until(settled, timeout=60), statuses(client)
    return counts.pop()


def owner(client: TraversabilityClient) -> str:
    """The instance that answers for the robot's grid (its calibration comes from the owner)."""
    seen = statuses(client)
    owners = [name for name, s in seen.items() if CAMERA_SOURCE in s.sources and s.sources[CAMERA_SOURCE].processed]
    assert owners, seen
    return max(owners, key=lambda name: seen[name].sources[CAMERA_SOURCE].processed)


def same_figures(first: CalibrationReport, second: CalibrationReport) -> bool:
    return first.figures == second.figures and first.pairs_by_source == second.pairs_by_source


@pytest.fixture
def database() -> Iterator[PostgresCluster]:
    with postgres_cluster() as running:
        yield running


def test_the_fleets_pairs_survive_scale_down_and_a_full_restart(
    tiny_model_dir: Path, database: PostgresCluster
) -> None:
    url = database.create_database("fleet")
    router_port = free_port()
    router = start_router(router_port)
    root = Path(tempfile.mkdtemp(prefix="gcdtrav-fleet-"))
    fleet = Fleet(tiny_model_dir, router_port, database, url, root)
    client = TraversabilityClient(config=client_config(router_port), timeout=10.0)
    counts: list[int] = []
    try:
        fleet.start("a")
        fleet.start("b")
        assert wait_until(lambda: set(statuses(client)) == {"a", "b"}, timeout=180), "both instances up"
        robot = BusRobot(client, make_world(seed=0), timeout_s=60.0)
        end = robot.drive(DRIVE_S, seed=1)
        counts.append(settled_pairs(client, {"a", "b"}))
        assert counts[-1] > 0
        before = client.calibration(CAMERA_SOURCE)

        first_owner = owner(client)
        fleet.stop(first_owner)  # a scale-down: its pod and state dir go
        left = ({"a", "b"} - {first_owner}).pop()
        counts.append(settled_pairs(client, {left}))
        after = client.calibration(CAMERA_SOURCE)  # answered by the instance left
        assert same_figures(before, after), (before.figures, after.figures)

        fleet.start("c")  # a scale-up on an empty state dir: it reads the fleet's pairs at once
        assert wait_until(lambda: set(statuses(client)) == {left, "c"}, timeout=180)
        counts.append(settled_pairs(client, {left, "c"}))
        end = robot.drive(DRIVE_S, seed=2, start_stamp=end + 10.0)
        counts.append(settled_pairs(client, {left, "c"}))
        assert counts[-1] > counts[-2]
        before = client.calibration(CAMERA_SOURCE)

        for instance in (left, "c"):  # every instance goes: a full restart, every state dir empty
            fleet.stop(instance)
        fleet.start("d")
        fleet.start("e")
        assert wait_until(lambda: set(statuses(client)) == {"d", "e"}, timeout=180)
        counts.append(settled_pairs(client, {"d", "e"}))
        robot.drive(1.0, seed=3, start_stamp=end + 10.0)  # a few frames: the robot finds its owner
        counts.append(settled_pairs(client, {"d", "e"}))
        by_first, proposed_first = client.calibration(CAMERA_SOURCE), client.anchor_proposal()
        fleet.stop(owner(client))  # the other answers now
        by_second, proposed_second = client.calibration(CAMERA_SOURCE), client.anchor_proposal()
        assert same_figures(by_first, by_second)
        assert proposed_first.proposed == proposed_second.proposed  # the same fit of the same pairs
        assert (proposed_first.before, proposed_first.after) == (proposed_second.before, proposed_second.after)
        assert by_first.figures.pairs >= before.figures.pairs
        assert counts == sorted(counts), counts  # never dropped
        print(f"\nthe fleet's pairs at each step: {counts}")
    finally:
        client.close()
        fleet.close()
        router.kill()
        router.wait(timeout=20)
