"""Issue 56 end to end on loopback: the same simulated drive graded twice, once with the robot's commands and
odometry on the service's bus (the service's tracker), once on the robot's own bus behind `gcdtrav relay`
(the relay's tracker, batches over the link).

Tolerances: commands and odometry reach either tracker on two subscriber threads, so which one comes first at
the start of a window is the scheduler's (a command after the odometry sample it belongs to restarts the
window, counted ``not_commanded``), and a window is a distance driven (outcome_spacing_m): its phase can
shift by up to a window, and every later window with it (seen: 0.2-0.45 s). So: outcomes as many within 5 %,
each relayed outcome's score between those of the two outcomes on the bus around its stamp (to 0.1), pairs as
many within 10 %, and the calibration (MAE, bias) within 0.02."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import zenoh
from gcdtrav.client.relay.relay import Relay
from gcdtrav.client.session.zenoh_args import zenoh_config
from gcdtrav.schemas.experience import CalibrationFigures
from gcdtrav.schemas.relay import RelaySettings
from gcdtrav.schemas.settings import ExperienceSettings
from gcdtrav.service.store.opening import sqlite_file
from gcdtrav.service.store.records import PairColumns
from gcdtrav.service.store.sqlite import SqliteStore
from zenoh_helpers import connecting_config, free_port, subscribed_elsewhere, wait_until

from tests.service.bus.test_experience_e2e import running, settings
from tools.robot_drive import CAMERA_SOURCE, CMD_VEL_KEY, ODOMETRY_KEY, BusRobot, experience_settings
from tools.synthetic_scene import make_world, start_anchors

DRIVE_S, SEED = 40.0, 3
SCORE_TOLERANCE = 0.1


def drive_and_read(state: Path, through_relay: bool) -> tuple[PairColumns, dict[str, int], CalibrationFigures]:
    """The drive's pairs as the store keeps them, the experience's counts and its calibration."""
    # The drive runs about 13 x faster than its simulated clock: a batch half a second late is 6 s late in stamps.
    late = {"late_s": 300.0}
    experience = (
        experience_settings(cmd_vel=None, odometry=None, **late) if through_relay else experience_settings(**late)
    )
    world = make_world(seed=0)
    with running(settings(state, experience)) as (service, client, _):
        robot_port = free_port()
        bus = zenoh.open(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{robot_port}"], multicast_scouting=False))
        local = zenoh.open(connecting_config(robot_port, mode="client"))  # the relay's session of the robot's bus
        experience = service.experience
        assert experience is not None
        relay = None
        try:
            if through_relay:
                relay = Relay(
                    RelaySettings.model_validate(
                        {
                            "cameras": [{"camera": "robot/unused", "source": CAMERA_SOURCE, "frames": False}],
                            "safe_mask": {"enabled": False},
                            "outcomes": {"cmd_vel": CMD_VEL_KEY, "odometry": ODOMETRY_KEY, "batch_period_s": 0.5},
                        }
                    ),
                    link=client.session,
                    local=local,
                ).start()
                assert subscribed_elsewhere(bus, ODOMETRY_KEY, 30) and subscribed_elsewhere(bus, CMD_VEL_KEY, 30)
                assert subscribed_elsewhere(client.session, "gcdtrav/in/robot/cam/outcomes", 30)
            robot = BusRobot(client, world, robot_bus=bus if through_relay else None)
            robot.drive(DRIVE_S, seed=SEED)
            robot.close()
            counts = experience.experience.counts
            if relay is not None:  # the last batch leaves within batch_period_s, and is paired on arrival
                sent = relay.outcomes
                assert sent is not None
                assert wait_until(lambda: sent.sent == sent.measured, 30), (sent.sent, sent.measured)
                assert wait_until(lambda: counts().get("relayed_outcomes") == sent.sent, 30), counts()
            else:  # every outcome the service's tracker made is paired
                assert wait_until(lambda: counts().get("outcomes") == counts().get("velocity_outcomes"), 30), counts()
            assert experience.experience.flush(30.0)
            final = counts()
            figures = client.calibration(CAMERA_SOURCE).figures
        finally:
            if relay is not None:
                relay.close()
            local.close()
            bus.close()
    store = SqliteStore(sqlite_file(state, "gcdtrav"))
    try:
        return store.pairs(start_anchors().concepts), final, figures
    finally:
        store.close()


def around(outcomes: np.ndarray, stamp: float) -> np.ndarray:
    """The outcomes (stamp, score) just before and just after ``stamp`` (one where it lies outside them)."""
    after = int(np.searchsorted(outcomes[:, 0], stamp))
    return outcomes[max(0, after - 1) : after + 1]


def bracketed(score: float, neighbours: np.ndarray) -> bool:
    """A window shifted in phase spans parts of the two windows around its end: its mean score lies between
    theirs, to SCORE_TOLERANCE (the speed within a window is not uniform)."""
    scores = neighbours[:, 1]
    return bool(scores.min() - SCORE_TOLERANCE <= score <= scores.max() + SCORE_TOLERANCE)


def outcomes_of(pairs: PairColumns) -> np.ndarray:
    """The distinct outcomes (stamp, score) the pairs were made of, by stamp."""
    return np.unique(np.stack([pairs.stamps, pairs.outcomes], axis=1), axis=0)


def test_a_relayed_robot_and_a_robot_on_the_bus_make_the_same_pairs_for_the_same_drive(tmp_path: Path) -> None:
    began = time.monotonic()
    on_bus, bus_counts, bus_figures = drive_and_read(tmp_path / "bus", through_relay=False)
    relayed, relay_counts, relay_figures = drive_and_read(tmp_path / "relay", through_relay=True)
    print(f"\n{len(on_bus)} pairs on the bus, {len(relayed)} relayed ({time.monotonic() - began:.0f} s)")
    assert len(on_bus) > 50 and relay_counts.get("relayed_outcomes", 0) > 0 and "relayed_outcomes" not in bus_counts
    assert abs(len(relayed) - len(on_bus)) <= 0.1 * len(on_bus), (len(relayed), len(on_bus))
    bus_outcomes, relay_outcomes = outcomes_of(on_bus), outcomes_of(relayed)
    assert abs(len(relay_outcomes) - len(bus_outcomes)) <= max(2, 0.05 * len(bus_outcomes))
    started = max(bus_outcomes[0, 0], relay_outcomes[0, 0])  # each tracker's first window began when it began
    for stamp, score in relay_outcomes[relay_outcomes[:, 0] >= started]:
        assert bracketed(score, around(bus_outcomes, stamp)), (stamp, score, around(bus_outcomes, stamp))
    assert set(relayed.kinds.tolist()) == set(on_bus.kinds.tolist()) == {0}  # velocity
    assert set(relayed.versions) == set(on_bus.versions) and set(relayed.sources) == set(on_bus.sources) == {
        CAMERA_SOURCE
    }
    assert bus_figures.mae is not None and relay_figures.mae is not None
    assert abs(relay_figures.mae - bus_figures.mae) <= 0.02
    assert bus_figures.bias is not None and relay_figures.bias is not None
    assert abs(relay_figures.bias - bus_figures.bias) <= 0.02


def test_a_bad_batch_is_counted_and_loses_nothing_else(tmp_path: Path) -> None:
    """Garbage on the batches' key: rejected with its reason, the service serving on; a good batch after it pairs."""
    from gcdtrav.schemas.experience import OutcomeBatch, TraversalOutcome

    with running(settings(tmp_path / "state", ExperienceSettings(enabled=True))) as (service, client, _):
        key = "gcdtrav/in/robot/cam/outcomes"
        assert subscribed_elsewhere(client.session, key, 30)
        client.session.put(key, b"\x93not a batch")
        client.session.put(
            key, b'{"outcomes": [{"stamp": 1, "x": 0, "y": 0, "score": 7, "kind": "velocity"}], "sent_at": 1}'
        )
        good = OutcomeBatch(
            outcomes=[TraversalOutcome(stamp=1.0, x=0.0, y=0.0, score=1.0, kind="velocity")], sent_at=2.0
        )
        client.session.put(key, good.pack())
        experience = service.experience
        assert experience is not None
        assert wait_until(lambda: experience.experience.counts().get("relayed_outcomes", 0) == 1, 30)
        assert wait_until(lambda: client.status().rejected_by_reason.get("bad_outcome") == 2, 30)
        assert experience.experience.counts()["rejected_bad_outcome"] == 2
