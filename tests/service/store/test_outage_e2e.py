"""PostgreSQL stopped mid-drive and started again (issue 46, "Done when"): the robot gets every map meanwhile,
the status says the store is unreachable and since when, and every pair accepted during the outage is stored
afterwards; with a small outbox, the pairs beyond it are counted dropped, the rest stored."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from gcdtrav.client import TraversabilityClient
from gcdtrav.schemas.messages import StoreStatus
from gcdtrav.schemas.settings import load_settings
from gcdtrav.schemas.settings.store import PASSWORD_ENV
from postgres_cluster import PostgresCluster, postgres_cluster
from zenoh_helpers import connecting_config, wait_until

from tools.loopback import in_process_service
from tools.robot_drive import START_STAMP, BusRobot
from tools.synthetic_scene import SceneBackend, make_world, start_anchors

ROOT = Path(__file__).resolve().parents[3]
SETTINGS = ROOT / "examples" / "experience_drive.yaml"


@pytest.fixture
def database() -> Iterator[PostgresCluster]:
    with postgres_cluster() as running:
        yield running


OUTAGE_S = 30.0  # how long the database stays away in the large outbox's run (the bound's run ends when it drops)


@pytest.mark.parametrize("outbox_pairs", [100_000, 30])
def test_a_database_outage_mid_drive_costs_no_map_and_no_pair_within_the_bound(
    database: PostgresCluster, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, outbox_pairs: int
) -> None:
    url = database.create_database("outage")
    monkeypatch.setenv(PASSWORD_ENV, database.password)
    store = {"url": url, "outbox_pairs": outbox_pairs, "retry_s": 0.5, "connect_timeout_s": 2}
    settings = load_settings(SETTINGS, {"state_dir": str(tmp_path), "instance": "box", "store": store}, environ={})
    with (
        in_process_service(SceneBackend(), settings, start_anchors()) as (_, port),
        TraversabilityClient(config=connecting_config(port), timeout=10.0) as client,
    ):

        def state() -> StoreStatus:
            found = client.status().store
            assert found is not None
            return found

        robot = BusRobot(client, make_world(seed=0), timeout_s=30.0)
        failures: list[BaseException] = []
        legs: list[float] = []  # the last stamp of each leg driven
        arrived = threading.Event()

        def drive() -> None:
            """Legs of 2 simulated seconds until told to stop: the drive spans the outage however fast it runs."""
            try:
                end = START_STAMP
                while not arrived.is_set():
                    end = robot.drive(2.0, seed=len(legs), start_stamp=end + 1.0)  # a missed map raises
                    legs.append(end)
            except BaseException as err:  # reported below
                failures.append(err)

        driving = threading.Thread(target=drive)
        driving.start()
        assert wait_until(lambda: state().written_pairs > 0, timeout=60)
        database.stop()
        stopped_at = time.monotonic()
        assert wait_until(lambda: not state().reachable, timeout=30)
        down = state()
        assert down.unreachable_since is not None and down.error
        grown = wait_until(lambda: state().pending_pairs + state().dropped_pairs > down.pending_pairs + 20, 60)
        assert grown, (failures, state(), client.status().experience)  # the drive goes on, its pairs wait
        if outbox_pairs >= 100_000:  # the scenario: the database away for 30 s of a drive
            time.sleep(max(0.0, OUTAGE_S - (time.monotonic() - stopped_at)))
        during = state()
        database.start()
        driven = len(legs)
        assert wait_until(lambda: len(legs) >= driven + 2 or bool(failures), timeout=120)  # and on after it
        arrived.set()
        driving.join(timeout=300)
        assert not driving.is_alive() and failures == []  # no map missed, through the outage and after
        assert wait_until(lambda: state().reachable and state().pending_pairs == 0, timeout=60)
        after = client.status()
        assert after.store is not None and after.experience is not None
        assert after.experience.pairs == after.store.written_pairs  # one instance: its every accepted pair
        assert after.experience.counts["pairs"] == after.store.written_pairs
        if outbox_pairs < 100_000:
            assert during.pending_pairs <= outbox_pairs and after.store.dropped_pairs > 0
            assert after.experience.counts["dropped_store_outbox_full"] == after.store.dropped_pairs
        else:
            assert after.store.dropped_pairs == 0
