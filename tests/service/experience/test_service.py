"""The Experience facade the bus wiring will call: payloads in, pairs, reports, proposals and questions out."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest
from gcdtrav.schemas.anchors import Anchor, AnchorSet
from gcdtrav.schemas.experience import Odometry2D, OperatorAnswer, PlannedPath, TraversalOutcome
from gcdtrav.schemas.messages import MessageError, Pose2D
from gcdtrav.schemas.settings import AskSettings, ExperienceSettings, ServiceSettings, SettingsError
from gcdtrav.service.experience.service import Experience, service_experience
from gcdtrav.service.experience.store import OutcomeRejected
from gcdtrav.service.grid.fusion import GridSpec, GroundGrid
from gcdtrav.service.runtime.grids import GridOutputs
from gcdtrav.service.store.opening import service_outbox, sqlite_file
from gcdtrav.service.store.outbox import PairOutbox

from tools.loopback import sqlite_outbox
from tools.ros_fixtures import twist_cdr

ANCHORS = AnchorSet(anchors=[Anchor(concept="mud", position=0.1), Anchor(concept="grass", position=0.8)])
SETTINGS = ExperienceSettings(enabled=True, cmd_vel="/cmd_vel", odometry="robot/odom", footprint_m=0.2)


def outbox(path: Path | None = None) -> PairOutbox:
    """A SQLite store of its own, or the one at ``path`` (a restart)."""
    where = path or Path(tempfile.mkdtemp(prefix="gcdtrav-experience-")) / "store.sqlite3"
    return sqlite_outbox(where, 10_000, 10**7)


def ambiguous_strip(stamp: float) -> GroundGrid:
    grid = GroundGrid(GridSpec(size_m=10.0, resolution_m=0.1), 2)
    points = np.array([[x, 0.05] for x in np.arange(0.05, 4.0, 0.1) for _ in range(5)])
    grid.add(points, np.full((2, len(points)), 0.5, np.float32), stamp, ANCHORS)
    return grid


def test_commands_and_odometry_become_pairs_a_report_and_a_proposal(tmp_path: Path) -> None:
    path = sqlite_file(tmp_path, "gcdtrav/site")
    assert path.name == "gcdtrav_site.store.sqlite3"
    experience = Experience(SETTINGS, AskSettings(), "cam", tau=0.3, outbox=outbox(path))
    assert [(key, ros, reason) for key, ros, _, reason in experience.inputs()] == [
        ("/cmd_vel", True, "bad_cmd_vel"),
        ("robot/odom", False, "bad_odometry"),
    ]
    experience.on_grid_update("cam", ambiguous_strip(0.0), None)
    for k in range(80):  # 4 s at 0.5 m/s, commanded 1 m/s
        t = 2.5 + 0.05 * k
        experience.on_command(twist_cdr(1.0), t)
        experience.on_odometry(Odometry2D(stamp=t, x=0.5 * (t - 2.5), y=0.05, vx=0.5).pack(), t)
    report = experience.report(ANCHORS)
    assert report.figures.pairs > 0 and report.pairs_by_kind == {"velocity": report.figures.pairs}
    assert report.figures.mae == pytest.approx(abs(0.45 - 0.5), abs=1e-3)  # T 0.45, score 0.5
    assert experience.counts()["velocity_outcomes"] > 0
    proposal = experience.proposal(ANCHORS)
    assert proposal.source == "cam" and proposal.train_pairs > 0
    with pytest.raises(MessageError):
        experience.on_command(b"\x00garbage", 1.0)
    with pytest.raises(OutcomeRejected):
        experience.on_outcome(b'{"score": 2}')
    outcome = TraversalOutcome(stamp=3.0, x=1.05, y=0.05, score=0.1, kind="contact")
    assert experience.on_outcome(outcome.pack()) == 1
    assert experience.flush(5.0)
    experience.store.outbox.close()
    again = Experience(SETTINGS, AskSettings(), "cam", tau=0.3, outbox=outbox(path))
    assert again.report(ANCHORS).figures.pairs == report.figures.pairs + 1


def test_questions_and_answers_through_the_facade() -> None:
    ask = AskSettings(enabled=True, persist_s=1.0, min_cells=3)
    experience = Experience(ExperienceSettings(enabled=True), ask, "cam", tau=0.3, outbox=outbox())
    pose = Pose2D(stamp=0.0, x=0.0, y=0.0, yaw=0.0)
    assert experience.on_grid_update("cam", ambiguous_strip(0.0), pose) is None
    question = experience.on_grid_update("cam", ambiguous_strip(1.5), pose, crop=lambda region: b"jpeg")
    assert question is not None and question.crop_jpeg == b"jpeg"
    made = experience.on_answer(OperatorAnswer(id=question.id, source="cam", score=1.0).pack(), 9.0)
    assert made == len(question.cells)
    assert experience.report(ANCHORS).pairs_by_kind == {"operator": made}
    assert experience.counts()["ask_answered"] == 1
    with pytest.raises(ValueError, match="no questions are asked for source 'other'"):
        experience.on_answer(OperatorAnswer(id="x", source="other", score=1.0).pack(), 9.0)


def test_experience_off_makes_no_inputs() -> None:
    experience = Experience(ExperienceSettings(), AskSettings(), "cam", tau=0.3, outbox=outbox())
    assert experience.inputs() == []
    assert experience.on_grid_update("cam", ambiguous_strip(0.0), Pose2D(stamp=0, x=0, y=0, yaw=0)) is None


def test_a_planners_path_steers_where_questions_look_until_it_lapses() -> None:
    """The ambiguous strip lies along +x; the robot faces -y. Along its heading nothing is ahead; along a
    planner's path over the strip it is asked about; a path not renewed within path_timeout_s, or an empty one,
    gives the heading back."""
    now = [0.0]
    ask = AskSettings(enabled=True, persist_s=1.0, min_cells=3, path_timeout_s=5.0)
    on = ExperienceSettings(enabled=True)
    experience = Experience(on, ask, "cam", tau=0.3, outbox=outbox(), clock=lambda: now[0])
    facing_y = Pose2D(stamp=0.0, x=0.0, y=0.0, yaw=float(-np.pi / 2))
    for stamp in (0.0, 1.5):
        assert experience.on_grid_update("cam", ambiguous_strip(stamp), facing_y) is None

    along_x = PlannedPath(stamp=0.0, points=[(0.0, 0.0), (1.0, 0.05), (4.0, 0.05)])
    experience.on_planned_path("cam", along_x.pack(), received_at=now[0])
    assert experience.path_ahead("cam") == [(0.0, 0.0), (1.0, 0.05), (4.0, 0.05)]
    assert experience.on_grid_update("cam", ambiguous_strip(2.0), facing_y) is None  # flagged from now on
    question = experience.on_grid_update("cam", ambiguous_strip(3.5), facing_y)
    assert question is not None and all(x > 0 and abs(y) < 0.6 for x, y in question.cells)

    now[0] = 5.0
    assert experience.path_ahead("cam") is not None  # at the timeout, still held
    now[0] = 5.01
    assert experience.path_ahead("cam") is None  # lapsed: the heading again
    experience.on_planned_path("cam", along_x.pack(), received_at=now[0])
    experience.on_planned_path("cam", PlannedPath(stamp=1.0, points=[]).pack(), received_at=now[0])
    assert experience.path_ahead("cam") is None  # an empty path clears it
    with pytest.raises(MessageError):
        experience.on_planned_path("cam", b'{"stamp": 0, "points": [[1e9, 0], [0, 0]]}', received_at=now[0])
    with pytest.raises(MessageError):
        experience.on_planned_path("cam", b"\x00garbage", received_at=now[0])


def test_paths_are_held_for_so_many_sources_and_lapsed_ones_give_way(monkeypatch: pytest.MonkeyPatch) -> None:
    """Any name under {prefix}/in/ may send a path; before, every source's path was held for good."""
    from gcdtrav.service.experience import service

    monkeypatch.setattr(service, "MAX_PATH_SOURCES", 3)
    ask = AskSettings(enabled=True, path_timeout_s=5.0)
    experience = Experience(ExperienceSettings(enabled=True), ask, "cam", tau=0.3, outbox=outbox())
    path = PlannedPath(stamp=0.0, points=[(0.0, 0.0), (1.0, 0.0)]).pack()
    for index in range(3):
        experience.on_planned_path(f"r{index}/cam", path, received_at=float(index))
    with pytest.raises(MessageError, match="paths of 3 sources are held: no room for r3/cam's"):
        experience.on_planned_path("r3/cam", path, received_at=5.0)  # r0's lapses only after 5.0
    experience.on_planned_path("r0/cam", path, received_at=5.0)  # a held source renews whatever the count
    experience.on_planned_path("r3/cam", path, received_at=6.5)  # r1's lapsed (received at 1.0): it gives way
    assert sorted(experience._paths) == ["r0/cam", "r2/cam", "r3/cam"]


def test_after_fusion_snapshots_the_grid_and_a_failure_is_counted_not_raised(tmp_path: Path) -> None:
    grid = {"source": "cam", "intrinsics": {"fx": 40, "fy": 40, "cx": 32, "cy": 24, "width": 64, "height": 48},
            "mount": {"z": 1.0, "pitch": 0.5}, "size_m": 6.0, "resolution_m": 0.5}  # fmt: skip
    settings = ServiceSettings.model_validate({"state_dir": tmp_path, "grids": [grid], "experience": {"enabled": True}})
    rejected: list[tuple[str | None, str, str]] = []
    store = service_outbox(settings)
    experience = service_experience(
        settings, lambda name, reason, detail, _: rejected.append((name, reason, detail)), store
    )
    assert experience is not None and experience.source == "cam"
    assert store.location == str(sqlite_file(tmp_path, "gcdtrav")) and store.state().reachable
    fused = GridOutputs(settings.grids, 2, "test").sources["cam"]
    fused.grid, camera = ambiguous_strip(0.0), fused.cameras["cam"]  # as if a frame was fused
    assert experience.after_fusion(fused, camera, None) is None and len(experience.ring) == 1  # the snapshot
    experience.on_grid_update = lambda *args: 1 / 0  # type: ignore[method-assign,assignment,misc]
    assert experience.after_fusion(fused, camera, None) is None  # the frame's outputs go on
    assert rejected == [(None, "experience_failed", "cam: ZeroDivisionError: division by zero")]
    off = settings.model_copy(update={"experience": ExperienceSettings()})
    assert service_experience(off, lambda *args: None, store) is None
    with pytest.raises(SettingsError, match="grid 'nope' is not one of the grids"):
        service_experience(settings.model_copy(update={"experience": SETTINGS.model_copy(update={"grid": "nope"})}),
                           lambda *args: None, store)  # fmt: skip
