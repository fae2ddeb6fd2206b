"""The robot's guard of the speed mask (client/relay/mask_guard.py), on a clock the test moves: silence, late
masks, re-centring, recovery, and each setting at its edges."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest
import zenoh
from gcdtrav.client.relay.link import OnDemand
from gcdtrav.client.relay.mask_guard import LIVE, SAFE, WAITING, MaskGuard, floor_percent
from gcdtrav.client.relay.relay import Relay
from gcdtrav.client.session.zenoh_args import zenoh_config
from gcdtrav.schemas.relay import RelaySettings, RelaySettingsError, SafeMaskSettings, load_relay_settings
from gcdtrav.schemas.ros_nav import GridGeometry, occupancy_grid_cdr, speed_limit_cdr
from zenoh_helpers import fake_sample

LIVE_MASK = GridGeometry("odom", 0.25, 32, 32, (-4.0, -4.0), 100.0)


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def guard(**settings: float) -> tuple[MaskGuard, Clock]:
    clock = Clock()
    return MaskGuard("r1/front", SafeMaskSettings.model_validate(settings), clock), clock


def test_the_live_mask_stays_while_the_service_is_heard_and_the_safe_one_comes_after_the_silence() -> None:
    mask_guard, clock = guard(after_s=2.0, floor=0.25, max_speed_m_s=1.0, horizon_s=10.0, resolution_m=0.5)
    mask_guard.pose(3.0, -1.0, "odom")
    assert mask_guard.live_mask(LIVE_MASK, age_s=0.3) and mask_guard.state == LIVE
    for _ in range(10):  # credits and maps every 0.5 s: never quiet for 2 s
        clock.now += 0.5
        mask_guard.heard()
        assert mask_guard.due() is None
    clock.now += 2.0
    assert mask_guard.due() is None  # exactly after_s: not yet
    clock.now += 0.01
    safe = mask_guard.due()
    assert safe is not None and mask_guard.state == SAFE and "for 2.0 s" in (mask_guard.reason or "")
    # the floor everywhere, in the odometry's frame, centred on the robot, 2 x max speed x horizon each way
    assert safe.frame_id == "odom" and safe.percent == 25 and safe.resolution == 0.5
    assert safe.cells * safe.resolution == pytest.approx(2 * 2 * 1.0 * 10.0)
    assert safe.centre == pytest.approx((3.0, -1.0))
    assert (safe.values() == 25).all()
    assert mask_guard.due() is None  # handed out once per silence


def test_the_safe_mask_is_recentred_once_the_robot_came_halfway_to_its_rim() -> None:
    mask_guard, clock = guard(after_s=1.0, max_speed_m_s=1.0, horizon_s=10.0, resolution_m=1.0)
    mask_guard.pose(0.0, 0.0, "odom")
    clock.now += 1.5
    first = mask_guard.due()
    assert first is not None and first.centre == pytest.approx((0.0, 0.0))  # 40 m across: rim 20 m away
    mask_guard.pose(9.9, 0.0, "odom")
    assert mask_guard.due() is None
    mask_guard.pose(10.1, 0.0, "odom")  # over halfway (10 m) to the rim: it cannot leave it within the horizon
    second = mask_guard.due()
    assert second is not None and second.centre == pytest.approx((10.1, 0.0))
    mask_guard.pose(10.1, 0.0, "map")  # another frame: the mask follows it
    third = mask_guard.due()
    assert third is not None and third.frame_id == "map"
    assert mask_guard.safe_masks == 3


def test_the_safe_mask_is_recentred_while_the_service_is_heard_but_every_mask_comes_late() -> None:
    """A service too slow for after_s, or a grid that stopped fusing while credits and maps flow: before, the
    guard stayed quiet after the first safe mask while the robot drove off it."""
    mask_guard, clock = guard(after_s=1.0, max_speed_m_s=1.0, horizon_s=10.0, resolution_m=1.0)
    mask_guard.pose(0.0, 0.0, "odom")
    assert mask_guard.live_mask(LIVE_MASK, age_s=0.2)
    assert not mask_guard.live_mask(LIVE_MASK, age_s=3.0)  # late: the safe mask at once
    first = mask_guard.due()
    assert first is not None and first.centre == pytest.approx((0.0, 0.0)) and mask_guard.state == SAFE
    reason = mask_guard.reason
    centres = []
    for step in range(1, 301):  # 30 m at 1 m/s, a late mask and a credit every 0.1 s: never quiet
        clock.now += 0.1
        mask_guard.pose(0.1 * step, 0.0, "odom")
        assert not mask_guard.live_mask(LIVE_MASK, age_s=3.0)
        mask_guard.heard()
        handed = mask_guard.due()
        if handed is not None:
            centres.append(handed.centre[0])
    assert centres == pytest.approx([10.1, 20.2], abs=0.01)  # each time halfway to the rim (20 m across each way)
    assert mask_guard.state == SAFE and mask_guard.reason == reason and mask_guard.late_masks == 301


def test_a_fresh_mask_takes_over_at_once_and_a_late_one_never_does() -> None:
    mask_guard, clock = guard(after_s=2.0)
    mask_guard.pose(0.0, 0.0, "odom")
    clock.now += 3.0
    assert mask_guard.due() is not None and mask_guard.state == SAFE
    assert not mask_guard.live_mask(LIVE_MASK, age_s=2.5)  # a backlog flushed after the outage
    assert mask_guard.state == SAFE and mask_guard.late_masks == 1
    assert mask_guard.live_mask(LIVE_MASK, age_s=0.4)
    assert mask_guard.state == LIVE and mask_guard.reason is None and mask_guard.due() is None


def test_a_late_mask_while_live_puts_the_safe_mask_in_force_at_once() -> None:
    """The service's own mask came late (a slow service, or its safe mask of a stale grid, stamped with the grid's
    last capture): the live mask in force is older still, so the safe mask replaces it before any silence."""
    mask_guard, clock = guard(after_s=2.0)
    assert mask_guard.live_mask(LIVE_MASK, age_s=0.5)
    clock.now += 0.5
    assert not mask_guard.live_mask(LIVE_MASK, age_s=3.1)
    safe = mask_guard.due()  # no pose: centred on the last live mask, in its frame
    assert safe is not None and safe.centre == pytest.approx((0.0, 0.0)) and safe.frame_id == "odom"
    assert "came 3.1 s after its capture" in (mask_guard.reason or "")


def test_a_mask_of_unknown_age_is_fresh_and_a_service_never_heard_turns_safe_after_the_start() -> None:
    mask_guard, clock = guard(after_s=2.0)
    assert mask_guard.state == WAITING
    clock.now += 2.5
    assert mask_guard.due() is None  # no pose, no live mask: no frame to put a safe mask in
    assert "neither a pose nor a live mask" in (mask_guard.reason or "")
    mask_guard.pose(1.0, 2.0, "odom")
    safe = mask_guard.due()
    assert safe is not None and "nothing from the service" in safe.reason
    assert mask_guard.live_mask(LIVE_MASK, age_s=None)  # a relay that sent no frame cannot age a mask


def test_a_pose_that_is_not_finite_is_not_taken() -> None:
    mask_guard, clock = guard(after_s=1.0)
    mask_guard.pose(2.0, 2.0, "odom")
    mask_guard.pose(math.nan, 0.0, "odom")
    clock.now += 1.5
    safe = mask_guard.due()
    assert safe is not None and safe.centre == pytest.approx((2.0, 2.0))


@pytest.mark.parametrize(
    ("floor", "percent"),
    [(0.01, 1), (0.25, 25), (0.3, 30), (0.994, 99), (1.0, 0)],  # 1: "no limit", as the service writes it
)
def test_the_floor_as_a_mask_value(floor: float, percent: int) -> None:
    assert floor_percent(floor) == percent


def test_one_cell_at_the_smallest_reach() -> None:
    safe_guard, clock = guard(after_s=0.1, max_speed_m_s=0.01, horizon_s=0.01, resolution_m=100)
    safe_guard.pose(0.0, 0.0, "odom")
    clock.now += 1.0
    safe = safe_guard.due()
    assert safe is not None and safe.cells == 1


def test_settings_are_strict_and_the_mask_bounded() -> None:
    with pytest.raises(ValueError, match="raise resolution_m"):
        SafeMaskSettings(max_speed_m_s=10, horizon_s=600, resolution_m=0.5)
    with pytest.raises(ValueError):
        SafeMaskSettings.model_validate({"after_s": 0})
    with pytest.raises(ValueError):
        SafeMaskSettings.model_validate({"after": 2})


def test_a_cameras_own_guard_and_flags_on_top_of_the_files_section(tmp_path: object) -> None:
    from pathlib import Path

    file = Path(str(tmp_path)) / "relay.yaml"
    file.write_text(
        "cameras:\n"
        "  - {camera: a, source: r1/a}\n"
        "  - {camera: b, source: r1/b, frames: false, safe_mask: {after_s: 5}}\n"
        "safe_mask: {floor: 0.2, max_speed_m_s: 2}\n"
    )
    settings = load_relay_settings(file, {"safe_mask": {"after_s": 1.5}})
    first, second = settings.cameras
    assert settings.safe_mask_of(first) == SafeMaskSettings(after_s=1.5, floor=0.2, max_speed_m_s=2)
    # the camera's own field on top of the relay's: before, its section replaced the relay's whole (floor 0.3)
    assert settings.safe_mask_of(second) == SafeMaskSettings(after_s=5, floor=0.2, max_speed_m_s=2)
    assert not second.frames and first.frames
    with pytest.raises(RelaySettingsError, match=r"safe_mask\.after_s"):
        load_relay_settings(file, {"safe_mask": {"after_s": -1}})
    # valid alone, not on top of the relay's: said at load, naming the camera
    file.write_text(
        "cameras:\n  - {camera: b, source: r1/b, safe_mask: {horizon_s: 100}}\nsafe_mask: {max_speed_m_s: 10}\n"
    )
    with pytest.raises(RelaySettingsError, match=r"camera r1/b: .*cells a side"):
        load_relay_settings(file, {})


class SafeMasksPut:
    """The relay's robot side, recording what is put on it; a safe mask's put waits for ``release`` if given."""

    def __init__(self, release: threading.Event | None = None) -> None:
        self.put: list[str] = []
        self.putting, self.release = threading.Event(), release

    def outputs(self, relay: object, source: str) -> list[object]:
        return []

    def publish_safe_mask(self, mask: object) -> None:
        self.putting.set()
        if self.release is not None:
            assert self.release.wait(10)
        self.put.append("safe")


class RecordedOutput(OnDemand):
    """An output forwarded to the robot side: its deliveries recorded there."""

    def deliver(self, sample: object) -> float | None:
        robot = self.relay.robot  # type: ignore[attr-defined]
        robot.put.append(self.kind)
        return None


@contextmanager
def quiet_relay(robot: SafeMasksPut) -> Iterator[Relay]:
    """A relay of one camera whose service has been quiet for longer than after_s (0.05 s): a safe mask is due."""
    settings = RelaySettings.model_validate(
        {"cameras": [{"camera": "robot/cam", "source": "r1/front"}], "safe_mask": {"after_s": 0.05}}
    )
    session = zenoh.open(zenoh_config(mode="peer", multicast_scouting=False))
    try:
        relay = Relay(settings, session, robot=robot)  # type: ignore[arg-type]
        relay.guards["r1/front"].pose(0.0, 0.0, "odom")
        time.sleep(0.1)
        yield relay
    finally:
        session.close()


def fresh_mask() -> bytes:
    return occupancy_grid_cdr((int(time.time()), 0), "odom", 0.5, (0.0, 0.0), np.zeros((4, 4), np.int8))


def test_a_safe_mask_being_put_is_never_put_after_a_fresh_live_mask_that_came_meanwhile() -> None:
    """The relay's thread decides on the safe mask and puts it; a fresh live mask arriving on zenoh's thread in
    between waits its turn, so the robot ends with the live mask, as the guard says. Before, the live mask was
    delivered first and the safe one overwrote it: the robot stayed at the floor under a guard saying live."""
    release = threading.Event()
    robot = SafeMasksPut(release)
    with quiet_relay(robot) as relay:
        deciding = threading.Thread(target=relay._guard)
        deciding.start()
        assert robot.putting.wait(10)
        output = RecordedOutput(relay, "r1/front", "speed_mask")
        arriving = threading.Thread(target=output._arrived, args=[fake_sample(fresh_mask())])
        arriving.start()
        arriving.join(0.3)  # it waits for the safe mask's put
        release.set()
        deciding.join(10)
        arriving.join(10)
        assert robot.put == ["safe", "speed_mask"] and relay.guards["r1/front"].state == LIVE


def test_while_the_safe_mask_is_in_force_no_live_speed_limit_replaces_its_floor() -> None:
    robot = SafeMasksPut()
    with quiet_relay(robot) as relay:
        relay._guard()
        limit, mask = RecordedOutput(relay, "r1/front", "speed_limit"), RecordedOutput(relay, "r1/front", "speed_mask")
        no_limit = speed_limit_cdr((int(time.time()), 0), "odom", 0.0)
        limit._arrived(fake_sample(no_limit))  # not while safe
        mask._arrived(fake_sample(fresh_mask()))
        limit._arrived(fake_sample(no_limit))  # a fresh mask is in force: it flows
        assert robot.put == ["safe", "speed_mask", "speed_limit"] and relay.guards["r1/front"].state == LIVE
