"""Questions in a fleet (issue 47 item 8), two instances on loopback with experience and asking on: the grid's
source moves from one to the other, each asks about it, and their ids differ; the one the first asked stays
open there (nothing updates its grid any more) but is neither listed by the status nor what `gcdtrav answer
SOURCE` answers: the owner's is."""

from __future__ import annotations

import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import zenoh
from conftest import torch_free_gcdtrav
from gcdtrav.client import TraversabilityClient
from gcdtrav.schemas.experience import OperatorQuestion
from gcdtrav.schemas.settings import AskSettings, ServiceSettings
from gcdtrav.service.bus.node import TraversabilityService
from gcdtrav.service.pipeline import Pipeline
from gcdtrav.service.runtime.fleet.assignment import owner_of
from zenoh_helpers import client_config, free_port, start_router, subscribed_elsewhere, wait_until

from tools.robot_drive import CAMERA_SOURCE, BusRobot, experience_settings, grid_settings
from tools.synthetic_scene import SceneBackend, make_world, start_anchors

pytest.importorskip("torch")

ASK = AskSettings(enabled=True, u_band=(0.05, 1.0), persist_s=1.0, min_cells=3, min_interval_s=1000)


@contextmanager
def instance(name: str, state: Path, router_port: int) -> Iterator[TraversabilityService]:
    """An instance in this process on its own session, a client of the router (as pods are)."""
    settings = ServiceSettings(
        state_dir=state / name,
        instance=name,
        preview=False,
        max_frame_age_s=None,  # simulated time from a stamp in the past, like a replayed bag
        max_stamp_skew_s=None,
        grids=[grid_settings()],
        experience=experience_settings(),
        ask=ASK,
    )
    session = zenoh.open(client_config(router_port))
    try:
        service = TraversabilityService(session, Pipeline(SceneBackend(), start_anchors(), settings.engine), settings)
        service.start()
        try:
            yield service
        finally:
            service.stop()
    finally:
        session.close()


def drive_until_asked(robot: BusRobot, questions: list[OperatorQuestion], asked: int, start: float) -> float:
    """Drive legs of 20 s (simulated) until ``asked`` questions came; the last stamp."""
    for leg in range(6):
        start = robot.drive(20.0, seed=10 + leg, start_stamp=start) + 1.0
        if len(questions) >= asked:
            return start
    raise AssertionError(f"{len(questions)} question(s) after 120 s of driving, waited for {asked}")


def test_each_instance_asks_with_its_own_ids_and_answer_goes_to_the_owners_question(tmp_path: Path) -> None:
    first = "exp-a"
    second = next(
        name for name in ("exp-b", "exp-c", "exp-d", "exp-e") if owner_of(CAMERA_SOURCE, [first, name]) == name
    )
    port = free_port()
    router = start_router(port)
    try:
        with_two_instances(tmp_path, port, first, second)
    finally:
        router.terminate()
        router.wait(10)


def with_two_instances(tmp_path: Path, port: int, first: str, second: str) -> None:
    with (
        instance(first, tmp_path, port) as a,
        TraversabilityClient(config=client_config(port), timeout=5.0) as client,
    ):
        questions: list[OperatorQuestion] = []
        client.subscribe_questions("**", questions.append)
        # the client's questions subscription known to a's session: its first question is not lost
        assert subscribed_elsewhere(a.session, a.keys.question(CAMERA_SOURCE)), "the questions subscription"
        robot = BusRobot(client, make_world(seed=0))
        stamp = drive_until_asked(robot, questions, 1, 1.7e9)
        with instance(second, tmp_path, port) as b:
            # b serves the grid's source, as both see it, before the robot drives on
            assert wait_until(lambda: b.owns(CAMERA_SOURCE) and not a.owns(CAMERA_SOURCE), 60), "the source moved"
            drive_until_asked(robot, questions, 2, stamp + 10.0)
            asked_by_a, asked_by_b = questions[0], questions[-1]
            assert asked_by_a.id != asked_by_b.id, (asked_by_a.id, asked_by_b.id)  # both were 'robot/cam-1'
            assert a.experience is not None and a.experience.experience.open_questions()[0].id == asked_by_a.id
            listed = [q.id for s in client.statuses() if s.experience for q in s.experience.open_questions]
            assert listed == [asked_by_b.id]  # a's cannot be answered there any more: not listed
            flags = ["-m", "client", "-e", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"]
            done = subprocess.run(
                torch_free_gcdtrav("answer", CAMERA_SOURCE, "drivable", *flags),
                capture_output=True,
                text=True,
                timeout=60,
            )
            assert done.returncode == 0, done.stdout + done.stderr
            assert f"answered {asked_by_b.id} ({CAMERA_SOURCE}): score 1" in done.stdout
            assert b.experience is not None and b.experience.experience.counts()["ask_answered"] == 1
