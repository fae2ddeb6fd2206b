"""One box with defaults (docs/calibration.md, "Where pairs live"): `gcdtrav serve` over a state dir that an
older gcdtrav left (its msgpack pairs, its anchor state) puts the pairs into SQLite in the state dir and
grades them at once; a simulated drive adds to them; a restart keeps them. Nothing else set up."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from gcdtrav.client import ServiceError, TraversabilityClient
from gcdtrav.schemas.experience import CalibrationReport
from gcdtrav.schemas.settings import load_settings
from gcdtrav.service.store.legacy import IMPORTED_SUFFIX
from gcdtrav.service.store.opening import sqlite_file
from zenoh_helpers import connecting_config, wait_until

from tools.loopback import anchor_set_at_start, in_process_service
from tools.robot_drive import CAMERA_SOURCE, BusRobot
from tools.synthetic_scene import SceneBackend, make_world

ROOT = Path(__file__).resolve().parents[3]
FILES = Path(__file__).resolve().parent / "legacy_files"
SETTINGS = ROOT / "examples" / "experience_drive.yaml"
OLD_PAIRS_OF_THE_ACTIVE_TUPLE = 350  # write_them.py: the last 70 outcomes x 5 cells, with the active set's concepts


def test_defaults_import_the_old_pairs_into_sqlite_and_keep_them(tmp_path: Path) -> None:
    state = tmp_path / "state"
    state.mkdir()
    for name in ("gcdtrav.experience.msgpack", "gcdtrav.anchors.json", "gcdtrav.anchors-history.json"):
        shutil.copy(FILES / name, state / name)
    settings = load_settings(SETTINGS, {"state_dir": str(state), "instance": "box"}, environ={})
    assert settings.store.url is None  # nothing about the store is set
    with (
        in_process_service(SceneBackend(), settings, anchor_set_at_start(settings)) as (service, port),
        TraversabilityClient(config=connecting_config(port), timeout=10.0) as client,
    ):
        status = client.status()
        assert status.store is not None and status.store.backend == "sqlite" and status.store.reachable
        assert status.store.location == str(sqlite_file(state, "gcdtrav"))
        assert status.experience is not None and status.experience.pairs == 1250  # every tuple's
        report = client.calibration(CAMERA_SOURCE)
        assert report.figures.pairs == OLD_PAIRS_OF_THE_ACTIVE_TUPLE and report.pairs_by_source == {"robot/cam": 350}
        split = client.calibration(CAMERA_SOURCE, by_source=True)  # gcdtrav calibration --by-source
        assert split.by_source == {"robot/cam": report.figures} and report.by_source is None
        with pytest.raises(ServiceError, match=r"give by_source=true, window=all\|day\|hour or none"):
            client._query(client.keys.calibration(CAMERA_SOURCE), CalibrationReport, {"by_source": "maybe"})
        assert (state / f"gcdtrav.experience.msgpack{IMPORTED_SUFFIX}").is_file()
        assert not (state / "gcdtrav.experience.msgpack").exists()
        BusRobot(client, make_world(seed=0)).drive(8.0, seed=1)  # with the imported active set: its tuple
        assert wait_until(lambda: client.status().store.written_pairs > 0, timeout=60)  # type: ignore[union-attr]
        service.experience.experience.flush(10.0)  # type: ignore[union-attr]
        total = client.status().experience.pairs  # type: ignore[union-attr]
        assert total > 1250 and client.calibration(CAMERA_SOURCE).figures.pairs == OLD_PAIRS_OF_THE_ACTIVE_TUPLE + (
            total - 1250
        )
    with (
        in_process_service(SceneBackend(), settings, anchor_set_at_start(settings)) as (_, port),
        TraversabilityClient(config=connecting_config(port), timeout=10.0) as client,
    ):
        assert client.status().experience.pairs == total  # type: ignore[union-attr]
