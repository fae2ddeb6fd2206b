"""The experience on the bus (issue 33, docs/calibration.md): only wiring; ``Experience`` does the work.

Declared only with ``experience.enabled`` (off: nothing here runs, nothing changes):

  {prefix}/in/{source}/outcome        subscriber: TraversalOutcome (msgpack or JSON)
  {prefix}/in/{source}/outcomes       subscriber: OutcomeBatch, outcomes a relay measured on the robot
  {prefix}/in/{source}/answer         subscriber (OperatorAnswer put) and queryable (the answer as payload,
                                      replied with an AnswerReply)
  experience.cmd_vel, .odometry       subscribers: Twist2D / Odometry2D on a zenoh key, or a ROS topic (CDR)
  {prefix}/out/{source}/calibration   queryable: CalibrationReport of the active anchor set over the fleet's
                                      pairs (``by_source=true``: each source's figures too; ``window=day|hour``:
                                      the pairs appended in the last day or hour)
  {prefix}/config/anchors/proposal    queryable: AnchorProposal (``source=`` optional), never applied here
  {prefix}/config/experience/exclusions  queryable: ExclusionList; with an ExclusionRequest as payload, the
                                      robot excluded (or included again) first, recorded in the store
  {prefix}/config/experience/kept     queryable: StoreContents (`gcdtrav kept`)
  {prefix}/out/{source}/question      queryable: the open OperatorQuestion (`gcdtrav answer` shows its crop
                                      before answering); a new one is published with the grid update that asked
                                      it, by the runtime's outputs like every payload (``Experience.after_fusion``)

A bad message is rejected with its reason and counted in the service's stats (``bad_outcome``,
``oversized``, ``bad_cmd_vel``, ``bad_odometry``, ``bad_answer``, ``unknown_answer``, ``unknown_grid``).
The pairs go to the fleet's store through the service's outbox (service/store/outbox.py); a store that cannot
be read makes a calibration or proposal query an error naming it, nothing else.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable
from functools import partial
from typing import Any

import zenoh
from gcdtrav.schemas.experience import (
    AnchorProposal,
    AnswerReply,
    CalibrationFigures,
    CalibrationReport,
    ExclusionList,
    ExclusionRequest,
    ExclusionWord,
    StoreContents,
)
from gcdtrav.schemas.keys import Keys
from gcdtrav.schemas.messages import ExperienceStatus, MessageError
from gcdtrav.schemas.settings import RosInput, ServiceSettings
from gcdtrav.service.bus import replies
from gcdtrav.service.bus.guard import answering
from gcdtrav.service.bus.queryables import answer_later
from gcdtrav.service.experience.graded import WINDOW_HOURS
from gcdtrav.service.experience.service import Experience, decode_answer
from gcdtrav.service.experience.store import OutcomeRejected
from gcdtrav.service.ros.cdr import dds_type_name
from gcdtrav.service.runtime.errors import QueryError
from gcdtrav.service.runtime.fleet.anchor_switch import AnchorSwitch
from gcdtrav.service.runtime.queries import strict_parameters
from gcdtrav.service.runtime.stats import ServiceStats
from gcdtrav.service.store import StoreError

log = logging.getLogger("gcdtrav.service")
MAX_EXCLUSION_BYTES = 4096  # a robot's name, who and why
CLOSE_FLUSH_S = 5.0  # at shutdown, this instance's queued pairs get this long to reach the store
TWIST, ODOMETRY = "geometry_msgs/msg/Twist", "nav_msgs/msg/Odometry"


def ros_key(topic: str, msgtype: str, ros_inputs: list[RosInput]) -> str:
    """The key expression of a robot's ROS topic, in the layout and zenoh namespace of the service's first ROS
    input (rmw_zenoh, no namespace, when there is none): any domain and type hash."""
    layout, namespace = (ros_inputs[0].layout, ros_inputs[0].zenoh_namespace) if ros_inputs else ("rmw_zenoh", "")
    name = topic.strip("/")
    key = name if layout == "bridge" else f"*/{name}/{dds_type_name(msgtype)}/*"
    return f"{namespace}/{key}" if namespace else key


class ExperienceBus:
    def __init__(
        self,
        session: zenoh.Session,
        settings: ServiceSettings,
        experience: Experience,
        stats: ServiceStats,
        owns: Callable[[str], bool],
        anchors: AnchorSwitch,
    ) -> None:
        self.session, self.settings, self.stats, self.owns = session, settings, stats, owns
        self.keys = Keys(settings.prefix)
        self.experience = experience  # the grids were given its after_fusion: its questions leave with their maps
        # the active set graded, the history a proposal is judged against, the store it is kept in; its reader
        # runs the store's reads and the fits, never a zenoh callback thread
        self.anchors = anchors

    # ---- lifecycle -----------------------------------------------------------------------------------
    def start(self) -> list[Any]:
        """Declare the subscribers and queryables (returned, for the node to undeclare)."""
        declared: list[Any] = [
            self.session.declare_subscriber(
                self.keys.outcome("**"), partial(self._on_outcomes, "outcome", self.experience.on_outcome)
            ),
            self.session.declare_subscriber(
                self.keys.outcomes("**"), partial(self._on_outcomes, "outcomes", self.experience.on_outcomes)
            ),
            self.session.declare_subscriber(self.keys.answer("**"), self._on_answer_sample),
            self.session.declare_subscriber(self.keys.planned_path("**"), self._on_planned_path),
        ]
        for key, ros, handler, reason in self.experience.inputs():
            declared.append(
                self.session.declare_subscriber(self._input_key(key, ros), self._input_handler(handler, reason))
            )
        queryables = (
            (self.keys.answer("**"), self._on_answer_query, False),
            (self.keys.calibration("**"), self._on_calibration, False),
            (self.keys.anchor_proposal, self._on_proposal, False),
            (self.keys.question("**"), self._on_question, False),
            (self.keys.exclusions, self._on_exclusions, True),
            (self.keys.kept, self._on_kept, True),
        )
        for key, respond, complete in queryables:
            declared.append(self.session.declare_queryable(key, answering(respond, self.stats), complete=complete))
        outbox = self.experience.store.outbox
        log.info("experience: outcomes of grid %s, pairs stored in %s %s", self.experience.source, outbox.backend,
                 outbox.location)  # fmt: skip
        return declared

    def _input_key(self, key: str, ros: bool) -> str:
        """The key expression commands or odometry are read on: the key itself, or a ROS topic's keys."""
        if not ros:
            return key
        return ros_key(key, TWIST if key == self.settings.experience.cmd_vel else ODOMETRY, self.settings.ros_inputs)

    def reads(self) -> str:
        """For the `serving` log line: the grid, and where commands and odometry are read."""
        inputs = [
            f"{reason.removeprefix('bad_')} on {self._input_key(key, ros)}" + (f" (ROS topic {key})" if ros else "")
            for key, ros, _, reason in self.experience.inputs()
        ]
        return f"grid {self.experience.source}, " + (", ".join(inputs) or "outcomes from the bus only")

    def close(self) -> None:
        """Write the queued pairs (bounded); the node undeclares the entities and closes the store."""
        self.experience.flush(CLOSE_FLUSH_S)

    def status(self) -> ExperienceStatus:
        """The experience's status, with the open questions of the grids this instance owns: one it asked before
        its grid moved to another instance can no longer be answered here (answers go to the owner)."""
        status = self.experience.status()
        owned = [question for question in status.open_questions if self.owns(question.source)]
        return status.model_copy(update={"open_questions": owned})

    def calibration(self) -> CalibrationFigures | None:
        """The active anchor set graded by the fleet's pairs (the metrics' ECE and coverage); None while the
        store cannot be read."""
        try:
            return self.experience.report(self.anchors.head().anchor_set).figures
        except StoreError as err:
            log.warning("no calibration figures for the metrics: %s", err)
            return None

    # ---- inputs --------------------------------------------------------------------------------------
    def _input_handler(self, handler: Callable[[bytes, float], None], reason: str) -> Callable[[zenoh.Sample], None]:
        def handle(sample: zenoh.Sample) -> None:
            if not self.owns(self.experience.source):
                # Another instance fuses the grid now: its snapshots, not this one's from before it moved, are the
                # predictions to pair with, and it pairs the same commands and odometry (one pair per outcome).
                return
            try:
                handler(sample.payload.to_bytes(), time.time())
            except (MessageError, ValueError) as err:
                self.stats.rejected(None, reason, f"{sample.key_expr}: {err}"[:200])

        return handle

    def _grid_source(self, key: str, kind: str) -> str | None:
        """The source of an outcome or answer key if this instance collects it; counted when it names a grid
        this service has no experience of."""
        parsed = self.keys.input_message(key)
        if parsed is None or parsed[1] != kind or not self.owns(parsed[0]):
            return None
        if parsed[0] != self.experience.source:
            self.stats.rejected(None, "unknown_grid", f"{key}: this service collects grid '{self.experience.source}'")
            return None
        return parsed[0]

    def _on_outcomes(self, kind: str, take: Callable[[bytes], int], sample: zenoh.Sample) -> None:
        """An outcome (``kind`` outcome) or a relay's batch (outcomes) for ``take``; a bad one counted."""
        key = str(sample.key_expr)
        if self._grid_source(key, kind) is None:
            return
        try:
            take(sample.payload.to_bytes())
        except OutcomeRejected as err:
            self.stats.rejected(None, err.reason, f"{key}: {err}"[:200])

    def _on_planned_path(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        parsed = self.keys.input_message(key)
        if parsed is None or parsed[1] != "planned_path" or not self.owns(parsed[0]):
            return
        try:
            self.experience.on_planned_path(parsed[0], sample.payload.to_bytes(), time.time())
        except MessageError as err:
            self.stats.rejected(None, "bad_planned_path", f"{key}: {err}"[:200])

    def _answer(self, key: str, payload: bytes) -> AnswerReply:
        """An answer's outcomes paired; MessageError or ValueError (counted) for a bad or unknown one."""
        try:
            answer = decode_answer(payload)
        except MessageError as err:
            self.stats.rejected(None, "bad_answer", f"{key}: {err}"[:200])
            raise
        source = self.keys.input_message(key)
        if source is None or answer.source != source[0]:
            self.stats.rejected(None, "bad_answer", f"{key}: the answer names source '{answer.source}'")
            raise ValueError(f"the answer names source '{answer.source}', the key '{key}'")
        try:
            pairs = self.experience.on_answer(answer, time.time())
        except ValueError as err:
            self.stats.rejected(None, "unknown_answer", f"{key}: {err}"[:200])
            raise
        return AnswerReply(id=answer.id, source=answer.source, score=answer.score, pairs=pairs)

    def _on_answer_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        if self._grid_source(key, "answer") is not None:
            with contextlib.suppress(MessageError, ValueError):  # counted in _answer
                self._answer(key, sample.payload.to_bytes())

    def _on_answer_query(self, query: zenoh.Query) -> None:
        key = str(query.key_expr)
        if self._grid_source(key, "answer") is None:
            return
        replies.check_no_parameters(query)
        payload = query.payload.to_bytes() if query.payload is not None else b""
        try:
            reply = self._answer(key, payload)
        except (MessageError, ValueError) as err:
            raise QueryError(str(err)) from None
        replies.reply(query, key, reply)

    # ---- answers -------------------------------------------------------------------------------------
    def _on_calibration(self, query: zenoh.Query) -> None:
        key = str(query.key_expr)
        source = self.keys.source_of(key, "calibration")
        if source is None:
            raise QueryError(f"query one source's calibration, e.g. {self.keys.calibration(self.experience.source)}")
        if not self.owns(source):
            return
        replies.check_format(query)
        params = strict_parameters(replies.without_format(query), "by_source=true, window=all|day|hour (optional)")
        window = params.get("window", "all")
        if set(params) - {"by_source", "window"} or params.get("by_source", "false") not in ("true", "false"):
            raise QueryError(f"unknown parameter(s) {dict(params)}; give by_source=true, window=all|day|hour or none")
        if window not in WINDOW_HOURS:
            raise QueryError(f"window={window}: one of {', '.join(WINDOW_HOURS)}")
        if source != self.experience.source:
            raise QueryError(f"no experience of '{source}': this service collects grid '{self.experience.source}'")
        by_source = params.get("by_source") == "true"

        def report() -> CalibrationReport:
            try:
                return self.experience.report(self.anchors.head().anchor_set, by_source, window)
            except StoreError as err:
                raise QueryError(f"cannot read the pairs: {err}") from None

        self.anchors.read_later(report, answer_later(query, key, self.stats))

    def _on_question(self, query: zenoh.Query) -> None:
        key = str(query.key_expr)
        source = self.keys.source_of(key, "question")
        if source is None or not self.owns(source):
            return
        replies.check_no_parameters(query)
        try:
            question = self.experience.open_question(source)
        except ValueError as err:
            raise QueryError(str(err)) from None
        replies.reply(query, key, question)

    def _on_proposal(self, query: zenoh.Query) -> None:
        replies.check_format(query)
        params = strict_parameters(replies.without_format(query), "source=SOURCE (optional)")
        if set(params) - {"source"}:
            raise QueryError(f"unknown parameter(s) {sorted(set(params) - {'source'})}; give source=SOURCE or none")
        source = params.get("source", self.experience.source)
        if source != self.experience.source or not self.owns(source):
            return  # another instance's experience
        self.anchors.read_later(self._proposal, answer_later(query, self.keys.anchor_proposal, self.stats))

    def _on_exclusions(self, query: zenoh.Query) -> None:
        replies.check_format(query)
        strict_parameters(replies.without_format(query), "none (the request, if any, is the payload)")
        payload = query.payload.to_bytes() if query.payload is not None else b""
        try:
            request = ExclusionRequest.decode(payload, MAX_EXCLUSION_BYTES) if payload else None
        except (MessageError, ValueError) as err:
            self.stats.rejected(None, "bad_exclusion", str(err)[:200])
            raise QueryError(f"not an ExclusionRequest: {err}") from None

        def words() -> ExclusionList:
            store = self.experience.store
            try:
                found = (
                    store.exclusions()
                    if request is None
                    else store.exclude(request.robot, request.excluded, request.actor, request.reason)
                )
            except StoreError as err:
                raise QueryError(f"cannot reach the store: {err}") from None
            if request is not None:
                said = "excluded" if request.excluded else "included again"
                log.info("experience: robot %s %s by %r (%s)", request.robot, said, request.actor, request.reason)
            return ExclusionList(words=[ExclusionWord(**vars(word)) for word in found])

        self.anchors.read_later(words, answer_later(query, self.keys.exclusions, self.stats))

    def _on_kept(self, query: zenoh.Query) -> None:
        replies.check_no_parameters(query)

        def contents() -> StoreContents:
            try:
                return self.experience.store.contents()
            except StoreError as err:
                raise QueryError(f"cannot read the store: {err}") from None

        self.anchors.read_later(contents, answer_later(query, self.keys.kept, self.stats))

    def _proposal(self) -> AnchorProposal:
        """Fitted and judged against the active set and the history's (the verdict's "best in history" is among
        them), then kept in the store: on the anchor switch's reader."""
        past = [entry.anchor_set for entry in self.anchors.history().entries]
        try:
            proposal = self.experience.proposal(self.anchors.head().anchor_set, past)
        except ValueError as err:
            raise QueryError(str(err)) from None
        except StoreError as err:
            raise QueryError(f"cannot read the pairs: {err}") from None
        return self.anchors.keep_proposal(proposal)


def experience_bus(
    session: zenoh.Session,
    settings: ServiceSettings,
    experience: Experience | None,
    stats: ServiceStats,
    owns: Callable[[str], bool],
    anchors: AnchorSwitch,
) -> ExperienceBus | None:
    """The experience's wiring, or None when ``experience.enabled`` is off (no experience)."""
    if experience is None:
        return None
    return ExperienceBus(session, settings, experience, stats, owns, anchors)
