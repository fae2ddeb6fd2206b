"""Issue 33 end to end on loopback: a service with experience on, a ground grid, the synthetic scene's backend,
a simulated robot publishing images, its pose, velocity commands and odometry over zenoh; the torch-free
commands an operator runs (`gcdtrav calibration`, `anchors propose [--apply]`, `answer`, `status`)."""

from __future__ import annotations

import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import zenoh
from conftest import torch_free_gcdtrav
from gcdtrav.client import QueryTimeout, ServiceError, TraversabilityClient, zenoh_config
from gcdtrav.schemas.anchors import Anchor, AnchorSet
from gcdtrav.schemas.experience import OperatorQuestion, TraversalOutcome
from gcdtrav.schemas.settings import AskSettings, ExperienceSettings, ServiceSettings
from gcdtrav.service.bus.node import TraversabilityService
from gcdtrav.service.pipeline import Pipeline
from gcdtrav.service.store.opening import sqlite_file
from zenoh_helpers import connecting_config, free_port, service_reachable, subscribed_elsewhere, wait_until

from tools.loopback import anchor_set_at_start, in_process_service
from tools.robot_drive import CAMERA_SOURCE, CMD_VEL_KEY, START_STAMP, BusRobot, experience_settings, grid_settings
from tools.synthetic_scene import SceneBackend, make_world, start_anchors

ASK = AskSettings(enabled=True, u_band=(0.05, 1.0), persist_s=1.0, min_cells=3, min_interval_s=1000)


def settings(state: Path, experience: ExperienceSettings | None = None, ask: AskSettings = ASK) -> ServiceSettings:
    """Simulated time from a stamp in the past, like a replayed bag: no age or skew checks."""
    return ServiceSettings(
        state_dir=state,
        instance="exp-1",
        preview=False,
        max_frame_age_s=None,
        max_stamp_skew_s=None,
        grids=[grid_settings()],
        experience=experience or experience_settings(),
        ask=ask,
    )


@contextmanager
def running(
    service_settings: ServiceSettings, anchors: AnchorSet | None = None
) -> Iterator[tuple[TraversabilityService, TraversabilityClient, list[str]]]:
    """The service, a client of it, and the flags that point `gcdtrav` at it."""
    with (
        in_process_service(SceneBackend(), service_settings, anchors or start_anchors()) as (service, port),
        TraversabilityClient(config=connecting_config(port), timeout=5.0) as client,
    ):
        # The service answers once it serves: its subscriptions (declared before its queryables, on the same
        # link) are known to the client then, and the tests' first puts are not lost (they were put at once).
        assert wait_until(lambda: service_reachable(client), 60), "the service did not answer"
        yield service, client, ["-m", "client", "-e", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"]


def gcdtrav(*args: str) -> subprocess.CompletedProcess[str]:
    """`gcdtrav ARGS` in a fresh interpreter where torch cannot be imported: the operator's install."""
    done = subprocess.run(torch_free_gcdtrav(*args), capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr
    return done


def test_drive_calibrate_ask_answer_propose_apply_restart(tmp_path: Path) -> None:
    state = tmp_path / "state"
    world = make_world(seed=0)
    with running(settings(state)) as (service, client, flags):
        questions: list[OperatorQuestion] = []
        client.subscribe_questions("**", questions.append)
        robot = BusRobot(client, world)
        end = robot.drive(90.0, seed=1)

        report = client.calibration(CAMERA_SOURCE)
        assert report.figures.pairs > 100 and report.pairs_by_kind == {"velocity": report.figures.pairs}
        assert report.concepts == start_anchors().concepts and report.figures.mae is not None
        assert report.pairs_by_version == {start_anchors().version: report.figures.pairs}
        shown = gcdtrav("calibration", "--png", str(tmp_path / "reliability.png"), *flags)  # the source from status
        assert f"calibration of {CAMERA_SOURCE}: anchor set {start_anchors().version}" in shown.stdout
        verdict, step = shown.stdout.splitlines()[-3:-1]  # the last line says where the diagram went
        assert verdict.startswith("verdict: over-confident (")  # sand, said 0.4, is 0.15: below tau more often
        assert "of the outcomes, promised" in verdict and "more often than said" in verdict
        assert step.startswith("next: gcdtrav anchors propose")
        assert (tmp_path / "reliability.png").read_bytes()[:4] == b"\x89PNG"

        # Ambiguity persisted ahead (dirt against gravel, sand against dirt): one question, with its crop.
        assert wait_until(lambda: questions, 60)
        question = questions[0]
        assert question.source == CAMERA_SOURCE and question.crop_jpeg and question.crop_jpeg[:2] == b"\xff\xd8"
        status = gcdtrav("status", *flags).stdout
        assert f"QUESTION {question.id} ({CAMERA_SOURCE})" in status and "velocity_outcomes" in status
        assert client.question(CAMERA_SOURCE) == question  # the open one, crop included, for a late operator
        crop = tmp_path / "crop.jpg"
        shown = gcdtrav("answer", CAMERA_SOURCE, "--save-crop", str(crop), *flags).stdout  # no answer: only shown
        assert (
            crop.read_bytes() == question.crop_jpeg and f"an answer makes {len(question.cells)} operator pairs" in shown
        )
        assert shown.splitlines()[-1].startswith("nothing recorded: ")
        assert client.status().experience.open_questions[0].cells == len(question.cells)  # type: ignore[union-attr]
        answered = gcdtrav("answer", CAMERA_SOURCE, "blocked", *flags).stdout
        assert f"answered {question.id} ({CAMERA_SOURCE}): score 0, {len(question.cells)} pairs" in answered
        experience = client.status().experience
        assert experience is not None and experience.open_questions == [] and experience.counts["ask_answered"] == 1
        assert client.calibration(CAMERA_SOURCE).pairs_by_kind["operator"] == len(question.cells)
        with pytest.raises(ServiceError, match="no open question"):  # answered: closed
            client.answer(CAMERA_SOURCE, question.id, 1.0)

        before = service.pipeline.anchors
        dry = gcdtrav("anchors", "propose", *flags).stdout
        assert f"{before.version} (8 anchors) -> " in dry and "~ sand @ 0.40 -> " in dry and "not applied" in dry
        assert "before (current set)" in dry and service.pipeline.anchors == before
        proposal = client.anchor_proposal()
        assert proposal.verdict is not None and proposal.verdict.applicable  # the fit beats the start set
        assert "verdict: better on the held-out pairs: mae " in dry
        assert proposal.kept and f"gcdtrav anchors apply {proposal.proposed_version} swaps in exactly" in dry
        reviewed = proposal.train_pairs + proposal.held_out_pairs
        end = robot.drive(20.0, seed=3, start_stamp=end + 5.0)  # pairs arrive between review and apply
        assert wait_until(lambda: client.calibration(CAMERA_SOURCE).figures.pairs > reviewed, 60)
        refit = client.anchor_proposal()  # what a refit at apply time would have swapped in
        assert refit.train_pairs + refit.held_out_pairs > reviewed
        assert refit.proposed_version != proposal.proposed_version
        applied = gcdtrav("anchors", "apply", proposal.proposed_version, *flags).stdout  # the reviewed one
        assert f"swapped: anchor set {proposal.proposed.version} active on exp-1" in applied
        assert service.pipeline.anchors == proposal.proposed  # exactly the reviewed set, not the refit
        assert client.anchor_history()[0].entries[1].anchor_set == before  # rollback-able
        assert client.anchor_history()[0].entries[0].how == "proposal"

        robot.drive(30.0, seed=2, start_stamp=end + 10.0)  # the same concepts: one tuple, two versions
        report = client.calibration(CAMERA_SOURCE)
        assert report.anchor_set_version == proposal.proposed.version
        assert set(report.pairs_by_version) == {before.version, proposal.proposed.version}
        total = report.figures.pairs
    assert sqlite_file(state, "gcdtrav").is_file()

    restarted = settings(state)
    with running(restarted, anchor_set_at_start(restarted)) as (_, client, _flags):  # as `gcdtrav serve` starts
        report = client.calibration(CAMERA_SOURCE)
        assert report.figures.pairs == total and report.anchor_set_version == proposal.proposed.version


def test_a_swap_to_other_concepts_keeps_their_pairs_apart(tmp_path: Path) -> None:
    start = start_anchors()
    fewer = AnchorSet(name="no-water", anchors=[Anchor(concept=c, position=p) for c, p in
                                                zip(start.concepts[1:], start.positions[1:], strict=True)])  # fmt: skip
    with running(settings(tmp_path, ask=AskSettings())) as (_, client, _flags):
        robot = BusRobot(client, make_world(seed=3))
        end = robot.drive(30.0, seed=4)
        first = client.calibration(CAMERA_SOURCE)
        client.set_anchors(fewer)
        end = robot.drive(30.0, seed=5, start_stamp=end + 10.0)
        other = client.calibration(CAMERA_SOURCE)
        assert other.concepts == fewer.concepts and other.pairs_by_version == {fewer.version: other.figures.pairs}
        assert other.figures.pairs > 0 and [a.concept for a in other.figures.anchors] == fewer.concepts
        client.set_anchors(start)
        again = client.calibration(CAMERA_SOURCE)
        # Back on the first tuple: its pairs, and only its own (outcomes of the first seconds after the swap
        # paired with the grid as it stood before it, fused with the first set).
        assert again.concepts == start.concepts and set(again.pairs_by_version) == {start.version}
        assert again.figures.pairs >= first.figures.pairs
        assert again.figures.pairs + other.figures.pairs == client.status().experience.pairs  # type: ignore[union-attr]


def test_bad_messages_are_rejected_counted_and_never_taken_for_images(tmp_path: Path) -> None:
    with running(settings(tmp_path, ask=AskSettings(path_timeout_s=600))) as (service, client, _flags):
        session = client.session
        session.put(client.keys.planned_path(CAMERA_SOURCE), b'{"stamp": 0, "points": [[0, 0], ["far", 1]]}')
        client.publish_planned_path(CAMERA_SOURCE, [(0.0, 0.0), (2.5, 0.5)])
        session.put(client.keys.outcome(CAMERA_SOURCE), b"\x00garbage")
        session.put(client.keys.outcome(CAMERA_SOURCE), b'{"stamp": 1, "x": 0, "y": 0, "score": 2, "kind": "velocity"}')
        session.put(client.keys.outcome(CAMERA_SOURCE), b"{" + b" " * 5000 + b"}")
        session.put(CMD_VEL_KEY, b'{"vx": "fast"}')
        session.put(client.keys.answer(CAMERA_SOURCE), b"\x01")
        outcome = TraversalOutcome(stamp=START_STAMP, x=0.0, y=0.0, score=0.5, kind="contact")
        client.publish_outcome("other/cam", outcome)  # a grid this service has no experience of
        client.publish_outcome(CAMERA_SOURCE, outcome)  # nothing fused yet: no prediction to pair with
        expected = {"bad_outcome": 2, "oversized": 1, "bad_cmd_vel": 1, "bad_answer": 1, "unknown_grid": 1}
        expected["bad_planned_path"] = 1

        def counted() -> bool:
            rejected = client.status().rejected_by_reason
            return all(rejected.get(reason) == n for reason, n in expected.items())

        assert wait_until(counted, 60), client.status().rejected_by_reason
        status = client.status()
        assert status.sources == {} and status.experience is not None  # no image source 'robot/cam/outcome'
        assert service.experience is not None  # the good path reached the experience: questions look along it
        assert service.experience.experience.path_ahead(CAMERA_SOURCE) == [(0.0, 0.0), (2.5, 0.5)]
        assert status.experience.counts["ignored_no_prediction"] == 1 and status.experience.pairs == 0
        with pytest.raises(ServiceError, match="no questions are asked"):
            client.answer(CAMERA_SOURCE, "robot/cam-1", 1.0)
        with pytest.raises(ServiceError, match="no experience of 'other/cam'"):
            client.calibration("other/cam")
        with pytest.raises(ServiceError, match="no pairs"):
            client.anchor_proposal()
        with pytest.raises(ServiceError, match=f"no open question for '{CAMERA_SOURCE}'"):
            client.question(CAMERA_SOURCE)
        assert client.calibration(CAMERA_SOURCE).figures.pairs == 0


def test_experience_off_declares_nothing_and_changes_nothing(tmp_path: Path) -> None:
    off = settings(tmp_path, ExperienceSettings(), AskSettings())
    with running(off) as (service, client, _flags):
        assert service.experience is None and client.status().experience is None
        BusRobot(client, make_world(seed=0)).drive(5.0, seed=1)  # images and grids flow as ever
        client.publish_outcome(CAMERA_SOURCE, TraversalOutcome(stamp=START_STAMP, x=0, y=0, score=1, kind="contact"))
        assert wait_until(lambda: client.status().rejected_by_reason.get("experience_off") == 1, 60)
        assert set(client.status().sources) == {CAMERA_SOURCE}
        with pytest.raises(QueryTimeout):
            client.calibration(CAMERA_SOURCE, timeout=0.5)
        with pytest.raises(QueryTimeout):
            client.anchor_proposal(timeout=0.5)
        with pytest.raises(QueryTimeout):
            client.question(CAMERA_SOURCE, timeout=0.5)
        store = client.status().store  # the store holds the anchor history: opened, with experience off too
        assert store is not None and store.reachable and store.written_pairs == 0


def test_settings_that_cannot_work_are_refused_at_start(tmp_path: Path) -> None:
    from gcdtrav.schemas.settings import SettingsError, load_settings

    with pytest.raises(SettingsError, match="experience: enabled needs a ground grid"):
        load_settings(None, {"experience": {"enabled": True}}, environ={})
    with pytest.raises(SettingsError, match="ask: enabled needs experience"):
        load_settings(None, {"ask": {"enabled": True}}, environ={})
    with (
        pytest.raises(SettingsError, match="grid 'nope' is not one of the grids"),
        running(settings(tmp_path, experience_settings(grid="nope"))),
    ):
        pass


def test_ros_topics_are_read_as_cdr_on_rmw_zenoh_keys(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    from gcdtrav.service.bus.experience import ros_key
    from gcdtrav.service.ros.cdr import RosTopic, topic_key

    from tools.ros_fixtures import odometry_cdr, twist_cdr

    ros = experience_settings(cmd_vel="/robot/cmd_vel", odometry="/robot/odom")
    expression = "*/robot/cmd_vel/geometry_msgs::msg::dds_::Twist_/*"
    assert ros_key("/robot/cmd_vel", "geometry_msgs/msg/Twist", []) == expression
    caplog.set_level("INFO", logger="gcdtrav.service")
    with running(settings(tmp_path, ros, AskSettings())) as (_, client, _flags):
        serving = next(r.getMessage() for r in caplog.records if r.getMessage().startswith("serving: "))
        assert f"grids {CAMERA_SOURCE} (pose on robot/pose (gcdtrav)), " in serving  # where the grid and the
        assert (  # experience read what they read: the first thing to check when nothing pairs
            f"experience grid {CAMERA_SOURCE}, cmd_vel on {expression} (ROS topic /robot/cmd_vel), "
            "odometry on */robot/odom/nav_msgs::msg::dds_::Odometry_/* (ROS topic /robot/odom), model "
        ) in serving
        twist = topic_key(RosTopic("/robot/cmd_vel", "geometry_msgs/msg/Twist", "rmw_zenoh", domain=7))
        odometry = topic_key(RosTopic("/robot/odom", "nav_msgs/msg/Odometry", "rmw_zenoh", domain=7))
        for key in (twist, odometry):  # the service's ROS subscriptions known here: no put is lost
            assert subscribed_elsewhere(client.session, key), key
        # The robot drives at 20 Hz, commanded 1 m/s, at 0.5 m/s: an outcome every 0.3 m (no grid: no pairs) once
        # its commands are in force. Paced like a robot: commands and odometry are handled on two threads, and a
        # burst of 2 s of driving put in a few ms was graded before a command was recorded (loaded, a full run).
        for k in range(1200):
            client.session.put(twist, twist_cdr(1.0))
            client.session.put(odometry, odometry_cdr(START_STAMP + 0.05 * k, 0.025 * k, 0.0, 0.0, 0.5))
            if k % 20 == 19 and "outcomes" in client.status().experience.counts:  # type: ignore[union-attr]
                break
            time.sleep(0.05)
        else:
            pytest.fail(f"no outcome in 60 s of driving: {client.status().experience}")
        client.session.put(twist, b"\x00\x01garbage")
        client.session.put(odometry, b"\x00\x01garbage")

        def rejected() -> bool:
            reasons = client.status().rejected_by_reason
            return reasons.get("bad_cmd_vel") == 1 and reasons.get("bad_odometry") == 1

        assert wait_until(rejected, 60), client.status().rejected_by_reason


class OwnedLock:
    """A grid's lock that knows which thread holds it (threading.Lock only knows that one does)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.owner: int | None = None

    def __enter__(self) -> OwnedLock:
        self._lock.acquire()
        self.owner = threading.get_ident()
        return self

    def __exit__(self, *exc: object) -> None:
        self.owner = None
        self._lock.release()


class WatchedSession:
    """A zenoh session whose every call, and every put of a publisher declared on it, notes whether the calling
    thread holds a grid's lock (a zenoh call may block on the network: never under a runtime lock)."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session, self.locks, self.calls_under_lock = session, list[OwnedLock](), list[str]()

    def check(self, call: str) -> None:
        if any(lock.owner == threading.get_ident() for lock in self.locks):
            self.calls_under_lock.append(f"{call} on {threading.current_thread().name}")

    def __getattr__(self, name: str) -> Any:
        found = getattr(self.session, name)
        if not callable(found):
            return found

        def call(*args: Any, **kwargs: Any) -> Any:
            self.check(f"session.{name}")
            result = found(*args, **kwargs)
            return WatchedPublisher(result, self) if name == "declare_publisher" else result

        return call


class WatchedPublisher:
    def __init__(self, publisher: zenoh.Publisher, session: WatchedSession) -> None:
        self.publisher, self.session = publisher, session

    def put(self, *args: Any, **kwargs: Any) -> None:
        self.session.check(f"put on {self.publisher.key_expr}")
        self.publisher.put(*args, **kwargs)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.publisher, name)


def test_no_zenoh_call_runs_under_a_grid_lock_questions_included(tmp_path: Path) -> None:
    """The operator's question leaves with the frame's other payloads (FrameOutputs), not from under the lock
    of the grid whose fusion asked it."""
    port = free_port()
    listening = zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    with zenoh.open(listening) as real:
        session = WatchedSession(real)
        pipeline = Pipeline(SceneBackend(), start_anchors(), ServiceSettings().engine)
        service = TraversabilityService(session, pipeline, settings(tmp_path))  # type: ignore[arg-type]
        grids = service.runtime.grids
        assert grids is not None
        for grid in grids.sources.values():
            grid.lock = OwnedLock()  # type: ignore[assignment]
            session.locks.append(grid.lock)  # type: ignore[arg-type]
        service.start()
        try:
            with TraversabilityClient(config=connecting_config(port), timeout=5.0) as client:
                questions: list[OperatorQuestion] = []
                client.subscribe_questions("**", questions.append)
                BusRobot(client, make_world(seed=0)).drive(90.0, seed=1)
                assert wait_until(lambda: questions, 60)  # the fusion asked one: the path ran
        finally:
            service.stop()
    assert session.calls_under_lock == []


def test_an_operator_excludes_a_robot_and_includes_it_again_from_the_command(tmp_path: Path) -> None:
    """`gcdtrav exclusions --exclude ROBOT` (torch-free) records the word in the store, the next calibration
    names the robot excluded, a bad request is refused and counted, `--include` counts it again."""
    with running(settings(tmp_path)) as (service, client, flags):
        robot = CAMERA_SOURCE.split("/")[0]
        assert "no robot excluded" in gcdtrav("exclusions", *flags).stdout
        said = gcdtrav("exclusions", "--exclude", robot, "--reason", "invented outcomes", "--operator", "alice", *flags)
        assert f"{robot}" in said.stdout and "excluded" in said.stdout and "alice: invented outcomes" in said.stdout
        assert client.calibration(CAMERA_SOURCE).excluded_robots == [robot]
        assert service.experience is not None  # the word is in the store, for every instance
        assert [w.robot for w in service.experience.experience.store.exclusions() if w.excluded] == [robot]
        client.session.get(client.keys.exclusions, payload=b'{"robot": "a/b"}', timeout=2.0)  # not one chunk
        assert wait_until(lambda: client.status().rejected_by_reason.get("bad_exclusion") == 1, 30)
        again = client.exclusions(robot, excluded=False, actor="bob")
        assert again.excluded == [] and again.words[0].actor == "bob"
        assert client.calibration(CAMERA_SOURCE).excluded_robots == []


def test_calibration_windows_over_the_bus_and_a_bad_window_refused(tmp_path: Path) -> None:
    with running(settings(tmp_path)) as (_service, client, flags):
        for window in ("all", "day", "hour"):
            assert client.calibration(CAMERA_SOURCE, window=window).figures.pairs == 0
        with pytest.raises(ServiceError, match="window=week: one of all, hour, day"):
            client.calibration(CAMERA_SOURCE, window="week")
        assert "calibration of" in gcdtrav("calibration", CAMERA_SOURCE, "--window", "day", *flags).stdout


def test_an_operator_sees_what_the_store_keeps(tmp_path: Path) -> None:
    with running(settings(tmp_path)) as (_service, client, flags):
        BusRobot(client, make_world(seed=0)).drive(8.0, seed=1)
        assert wait_until(lambda: client.kept().pairs > 0, 60)
        contents = client.kept()
        assert [k.source for k in contents.sources] == [CAMERA_SOURCE] and contents.sources[0].pairs == contents.pairs
        assert contents.max_pairs == 50_000 and contents.max_age_days is None
        text = gcdtrav("kept", *flags).stdout
        assert CAMERA_SOURCE in text and "raw pairs:" in text and "calibration sums" in text
