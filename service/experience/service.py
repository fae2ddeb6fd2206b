"""Everything the bus needs of issue 33 for one service, behind one object, so the wiring stays thin: it
subscribes to ``inputs()`` and hands payloads over, answers the calibration query with ``report`` and the
proposal with ``proposal``, and calls ``flush`` at shutdown. The grids call
``after_fusion`` under their lock after each fusion (given at their construction); the question it returns
leaves with the frame's grid, through the runtime's one hand-off out. No middleware here. Its pairs go to the
fleet's store (service/store/) through the outbox the service opened; reports and proposals read the fleet's.

One experience per service: the outcomes of ``experience.grid`` (the first grid when unset). Questions are
asked per grid that has a pose (``ask.enabled``).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence

import numpy as np
from gcdtrav.schemas.anchors import AnchorSet, default_anchor_set
from gcdtrav.schemas.experience import (
    AnchorProposal,
    CalibrationReport,
    OperatorAnswer,
    OperatorQuestion,
    PlannedPath,
)
from gcdtrav.schemas.messages import ExperienceStatus, MessageError, Pose2D, QuestionStatus
from gcdtrav.schemas.outcomes import MAX_INPUT_BYTES, VelocityTracker, decode_command, decode_odometry
from gcdtrav.schemas.settings import AskSettings, ExperienceSettings, ServiceSettings, SettingsError
from gcdtrav.service.experience.ask import Crop, OperatorAsker
from gcdtrav.service.experience.crop import image_crop
from gcdtrav.service.experience.fitter import BEST_IN_HISTORY, PAPER, FitOptions
from gcdtrav.service.experience.snapshots import SnapshotRing
from gcdtrav.service.experience.store import ExperienceStore
from gcdtrav.service.grid.fusion import GroundGrid
from gcdtrav.service.runtime.grids.state import CameraState, SourceGrid
from gcdtrav.service.store.outbox import PairOutbox
from numpy.typing import NDArray

log = logging.getLogger("gcdtrav.service")
MAX_PATH_SOURCES = 1024  # planned paths held at once (one per source)
ExperienceInput = tuple[str, bool, Callable[[bytes, float], None], str]  # key or topic, is ROS, handler, reason
# Counts a bad input (the service's ServiceStats.rejected): source or None, reason, detail, the error.
Rejected = Callable[[str | None, str, str, BaseException | None], None]


def is_ros_topic(name: str) -> bool:
    """Settings name a ROS topic with a leading '/' (read on its rmw_zenoh keys), a zenoh key without."""
    return name.startswith("/")


def decode_answer(payload: bytes) -> OperatorAnswer:
    """An OperatorAnswer in msgpack or JSON; MessageError if it is neither."""
    return OperatorAnswer.decode(payload, MAX_INPUT_BYTES)


def experience_grid(settings: ServiceSettings) -> str:
    """The grid the outcomes belong to: ``experience.grid``, else the first; a SettingsError without one."""
    names = [grid.source for grid in settings.grids]
    if not names:
        raise SettingsError("experience: enabled needs a ground grid (grids:): outcomes pair with its cells")
    wanted = settings.experience.grid or names[0]
    if wanted not in names:
        raise SettingsError(f"experience: grid '{wanted}' is not one of the grids {names}")
    return wanted


def service_experience(settings: ServiceSettings, rejected: Rejected, outbox: PairOutbox) -> Experience | None:
    """The service's experience (its pairs through ``outbox`` to the store), or None when ``experience.enabled``
    is off; a SettingsError when its grid is not configured."""
    if not settings.experience.enabled:
        return None
    grid, tau, instance = experience_grid(settings), settings.risk.tau, settings.instance
    return Experience(settings.experience, settings.ask, grid, tau, outbox, rejected=rejected, instance=instance)


class Experience:
    def __init__(
        self,
        settings: ExperienceSettings,
        ask: AskSettings,
        grid_source: str,
        tau: float,
        outbox: PairOutbox,
        clock: Callable[[], float] = time.time,
        rejected: Rejected | None = None,
        instance: str = "",
    ) -> None:
        """``outbox``: the way to the store; ``rejected``: where a failed ``after_fusion`` is counted (the
        service's stats), None: logged only; ``instance``: who pairs (kept with each pair)."""
        self.settings, self.ask_settings, self.source, self.tau, self.clock = settings, ask, grid_source, tau, clock
        self.rejected = rejected or _logged
        self.ring = SnapshotRing(
            settings.snapshot_every_s, int(settings.snapshot_budget_mb * 1e6), settings.lookahead_s + settings.late_s
        )
        self.store = ExperienceStore(
            outbox, grid_source, settings.lookahead_s, instance, clock, settings.max_robot_share, tau
        )
        self.tracker = VelocityTracker(settings)
        self.askers: dict[str, OperatorAsker] = {}
        # source -> (receipt, vertices): a planner's path ahead. Written by zenoh's callbacks, read by the worker;
        # each is one dict operation, whole tuples replaced, never mutated.
        self._paths: dict[str, tuple[float, list[tuple[float, float]]]] = {}

    # ---- inputs --------------------------------------------------------------------------------------
    def inputs(self) -> list[ExperienceInput]:
        """The command and odometry streams to subscribe to (zenoh keys or ROS topics), with their handlers
        and the reason a bad message is counted under. The outcome and answer keys are the bus's."""
        found: list[ExperienceInput] = []
        if self.settings.cmd_vel is not None:
            found.append((self.settings.cmd_vel, is_ros_topic(self.settings.cmd_vel), self.on_command, "bad_cmd_vel"))
        if self.settings.odometry is not None:
            found.append(
                (self.settings.odometry, is_ros_topic(self.settings.odometry), self.on_odometry, "bad_odometry")
            )
        return found

    def on_command(self, payload: bytes, received_at: float) -> None:
        """A velocity command; MessageError for a bad one (the bus counts it)."""
        assert self.settings.cmd_vel is not None
        self.tracker.on_command(decode_command(payload), received_at)  # CDR or msgpack/JSON, by their first bytes

    def on_odometry(self, payload: bytes, received_at: float) -> None:
        """An odometry sample; the outcome it closes is paired at once. MessageError for a bad one."""
        assert self.settings.odometry is not None
        outcome = self.tracker.on_odometry(decode_odometry(payload), received_at)
        if outcome is not None:
            self.store.add(outcome, self.ring)

    def on_outcome(self, payload: bytes) -> int:
        """An outcome from the bus ({prefix}/in/{source}/outcome); OutcomeRejected (counted) for a bad one."""
        return self.store.ingest(payload, self.ring)

    def on_outcomes(self, payload: bytes) -> int:
        """A relay's batch of outcomes measured on the robot ({prefix}/in/{source}/outcomes), paired as outcomes
        from the bus; OutcomeRejected (counted) for a bad batch; one whose outcomes were not all taken is counted
        once (bad_outcome), its others paired."""
        pairs, left_out = self.store.ingest_batch(payload, self.ring)
        if left_out:
            self.rejected(None, "bad_outcome", f"{left_out} outcomes of a batch not taken (the rest paired)", None)
        return pairs

    def on_answer(self, payload: bytes | OperatorAnswer, received_at: float) -> int:
        """An OperatorAnswer (msgpack or JSON, or decoded); the pairs its outcomes made. MessageError or ValueError
        (counted) if bad."""
        answer = payload if isinstance(payload, OperatorAnswer) else decode_answer(payload)
        asker = self.askers.get(answer.source)
        if asker is None:
            raise ValueError(f"no questions are asked for source '{answer.source}'")
        answered = asker.answer(answer, received_at)
        return sum(self.store.add_predicted(answered.weights[k : k + 1], answered.anchors, outcome)
                   for k, outcome in enumerate(answered.outcomes))  # fmt: skip

    def on_planned_path(self, source: str, payload: bytes, received_at: float) -> None:
        """A planner's path ahead of ``source``: questions look along it (an empty one: the heading again).
        MessageError for a bad one, or a new source's while MAX_PATH_SOURCES sources hold a path within
        ``ask.path_timeout_s`` (the bus counts it): any name under {prefix}/in/ may send one, and each held path
        costs up to MAX_INPUT_BYTES of memory."""
        path = PlannedPath.decode(payload, MAX_INPUT_BYTES)
        if len(path.points) < 2:
            self._paths.pop(source, None)
            return
        if source not in self._paths and len(self._paths) >= MAX_PATH_SOURCES:
            self._forget_lapsed_paths(received_at)
            if len(self._paths) >= MAX_PATH_SOURCES:
                raise MessageError(f"paths of {MAX_PATH_SOURCES} sources are held: no room for {source}'s")
        self._paths[source] = (received_at, [(float(x), float(y)) for x, y in path.points])

    def _forget_lapsed_paths(self, now: float) -> None:
        """Drop the paths not renewed within ``ask.path_timeout_s``: ``path_ahead`` no longer uses them."""
        for source, (received, _) in list(self._paths.items()):  # a copy: zenoh's callbacks may add meanwhile
            if self._lapsed(received, now):
                self._paths.pop(source, None)

    def _lapsed(self, received: float, now: float) -> bool:
        return now - received > self.ask_settings.path_timeout_s

    def path_ahead(self, source: str) -> list[tuple[float, float]] | None:
        """The planner's path of ``source`` if renewed within ``ask.path_timeout_s``; None: look along the heading."""
        held = self._paths.get(source)
        if held is None or self._lapsed(held[0], self.clock()):
            return None
        return held[1]

    # ---- the grid ------------------------------------------------------------------------------------
    def after_fusion(
        self, grid: SourceGrid, camera: CameraState, image: NDArray[np.uint8] | None
    ) -> OperatorQuestion | None:
        """Under the grid's lock, on the worker, right after it fused a frame (``GridOutputs``' ``after_fusion``):
        snapshot the grid, maybe ask, in memory only; the question goes out with the frame's grid. Never fails the
        frame's outputs: an error is counted (``experience_failed``) and no question asked."""
        source = grid.config.source
        pose = grid.fused_at.pose if grid.fused_at is not None else None  # the image's pose, not the newest
        try:
            crop = image_crop(image, pose, camera.mount, camera.camera)
            return self.on_grid_update(source, grid.grid, pose, crop)
        except Exception as err:
            self.rejected(None, "experience_failed", f"{source}: {type(err).__name__}: {err}"[:200], err)
            return None

    def on_grid_update(
        self, source: str, grid: GroundGrid, pose: Pose2D | None, crop: Crop | None = None
    ) -> OperatorQuestion | None:
        """After a grid fused a frame (under the grid's lock): snapshot it, track the ground ahead; a question
        to publish, or None."""
        if source == self.source:
            self.ring.capture(grid)
        if not self.ask_settings.enabled or pose is None:
            return None
        asker = self.askers.setdefault(source, OperatorAsker(source, self.ask_settings, self.tau))
        return asker.update(grid, pose, crop, self.path_ahead(source))

    # ---- answers -------------------------------------------------------------------------------------
    def report(self, anchors: AnchorSet, by_source: bool = False, window: str = "all") -> CalibrationReport:
        """The fleet's pairs of the set's tuple graded (``window``: all, day or hour); StoreUnavailable if the
        store cannot be read."""
        return self.store.report(anchors, self.tau, by_source, window)

    def proposal(self, anchors: AnchorSet, history: Sequence[AnchorSet] = ()) -> AnchorProposal:
        """Fitted to the pairs, judged against ``anchors`` (the active set), the paper's set and the best of
        ``history`` (the sets active before); ValueError without pairs of the set's concept tuple;
        StoreUnavailable if the store cannot be read."""
        options = FitOptions(
            tau=self.tau,
            held_out_fraction=self.settings.held_out_fraction,
            min_pairs_per_anchor=self.settings.min_pairs_per_anchor,
        )
        baselines = [(PAPER, default_anchor_set()), *((BEST_IN_HISTORY, past) for past in history)]
        return self.store.propose(self.source, anchors, options, baselines)

    def counts(self) -> dict[str, int]:
        """Every counter: the pairing's, the outbox's (store_*), the tracker's (velocity_*), the askers' (ask_*)."""
        found = dict(self.store.counts)
        outbox = self.store.outbox.state()
        found.update(store_written=outbox.written, store_dropped=outbox.dropped, store_evicted=outbox.evicted)
        found.update({f"velocity_{k}": v for k, v in self.tracker.counts.items()})
        for asker in self.askers.values():
            for name, value in asker.counts.items():
                found[f"ask_{name}"] = found.get(f"ask_{name}", 0) + value
        return found

    def open_questions(self) -> list[OperatorQuestion]:
        return [q for q in (asker.open_question for asker in list(self.askers.values())) if q is not None]

    def open_question(self, source: str) -> OperatorQuestion:
        """The open question about ``source``, crop included (for an operator to look before answering)."""
        for question in self.open_questions():
            if question.source == source:
                return question
        raise ValueError(f"no open question for '{source}' (questions are asked of grids with a pose)")

    def status(self) -> ExperienceStatus:
        """What ``gcdtrav status`` shows: the grid, the fleet's pairs, every counter, the open questions."""
        questions = [
            QuestionStatus(
                id=q.id, source=q.source, stamp=q.stamp, reason=q.reason, concepts=[c.concept for c in q.concepts],
                region=q.region, cells=len(q.cells),
            )
            for q in self.open_questions()
        ]  # fmt: skip
        totals = self.store.totals()
        return ExperienceStatus(
            source=self.source,
            pairs=totals.pairs,
            stored_bytes=totals.bytes,
            counts=self.counts(),
            open_questions=questions,
        )

    def flush(self, timeout_s: float) -> bool:
        """Wait until this instance's queued pairs are in the store; False if it did not take them in time."""
        return self.store.outbox.flush(timeout_s)


def _logged(name: str | None, reason: str, detail: str, error: BaseException | None) -> None:
    log.error("%s: %s: %s", name or "-", reason, detail, exc_info=error)
