"""The Zenoh node: a thin layer that wires the pipeline to keys on the bus.

Inputs (default gcdtrav/in/**): images as JPEG/PNG bytes or an ImageEnvelope, and ROS 2 topics. Every
output and queryable key is built by ``gcdtrav.schemas.keys.Keys`` (listed there and in docs/messages.md).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import zenoh
from gcdtrav.schemas.inputs import RejectedInput
from gcdtrav.schemas.keys import Keys, input_source_of, literal_head
from gcdtrav.schemas.messages import MessageError, ServiceStatus
from gcdtrav.schemas.settings import GridSettings, RosInput, ServiceSettings, SettingsError
from gcdtrav.service.bus import replies
from gcdtrav.service.bus.anchor_sync import AnchorSync
from gcdtrav.service.bus.credits import CreditPublisher
from gcdtrav.service.bus.entities import undeclare_all
from gcdtrav.service.bus.experience import experience_bus
from gcdtrav.service.bus.guard import answering
from gcdtrav.service.bus.membership import Membership
from gcdtrav.service.bus.outputs import FrameOutputs
from gcdtrav.service.bus.queryables import AnchorQueries, SourceQueries
from gcdtrav.service.bus.ros_graph import RosGraph
from gcdtrav.service.pipeline import Pipeline
from gcdtrav.service.ros import cdr as ros_io
from gcdtrav.service.runtime.admission import Admission
from gcdtrav.service.runtime.anchor_switch import AnchorSwitch
from gcdtrav.service.runtime.assignment import TABLE_IDLE_S, Assignment
from gcdtrav.service.runtime.credits import CreditLedger
from gcdtrav.service.runtime.frames import PendingFrame
from gcdtrav.service.runtime.freshness import FrameGate, Freshness
from gcdtrav.service.runtime.grids import GridOutputs
from gcdtrav.service.runtime.history import FrameHistory
from gcdtrav.service.runtime.intake_rate import IntakeRate
from gcdtrav.service.runtime.latest_queue import LatestFrameQueue
from gcdtrav.service.runtime.outputs import FramePublisher, OutputBuilder
from gcdtrav.service.runtime.probes import Probes
from gcdtrav.service.runtime.progress import Health, ProgressMonitor
from gcdtrav.service.runtime.reuse import ReuseTracker
from gcdtrav.service.runtime.share import policy_for
from gcdtrav.service.runtime.sources import SourceTracker
from gcdtrav.service.runtime.stats import ServiceStats
from gcdtrav.service.runtime.status import StatusParts
from gcdtrav.service.runtime.triage import Triage
from gcdtrav.service.runtime.worker import FrameWorker

log = logging.getLogger("gcdtrav.service")
WATCHDOG_INTERVAL_S = 0.25


def grids_described(grids: list[GridSettings]) -> str:
    """For the `serving` log line: each grid, the cameras it fuses and where its pose is read."""
    described = []
    for grid in grids:
        cameras = [camera.source for camera in grid.camera_list()]
        fused = f" of cameras {', '.join(cameras)}" if cameras != [grid.source] else ""
        pose = f"pose on {grid.pose_key} ({grid.pose_format})" if grid.pose_key else "no pose: the robot's frame"
        described.append(f"{grid.source}{fused} ({pose})")
    return "; ".join(described) or "none"


def publisher_of(sample: zenoh.Sample) -> str | None:
    """The publishing session's id if the publisher says (client/session/source_info.py); None: not capped."""
    info = sample.source_info
    return None if info is None else str(info.source_id.zid)


class TraversabilityService:
    def __init__(self, session: zenoh.Session, pipeline: Pipeline, settings: ServiceSettings) -> None:
        self.session = session
        self.pipeline = pipeline
        self.settings = settings
        self.prefix = settings.prefix
        self.keys = Keys(settings.prefix)
        self.history = FrameHistory(settings.history, round(settings.history_budget_mb * 1e6))
        self.stats = ServiceStats(log, settings.source_idle_s)
        self.intake_rate = IntakeRate(
            settings.intake_rate_per_publisher, settings.intake_rate_anonymous, settings.intake_burst_s
        )
        self._declared: list[Any] = []
        self._stopping = threading.Event()
        self.membership: Membership | None = None
        self._leaving: Callable[[str], bool] | None = None  # after stop(): what it owned when it left
        self.probes: Probes | None = None
        self.anchor_sync: AnchorSync | None = None
        self.anchor_switch = AnchorSwitch(
            pipeline, settings.state_file, settings.instance, settings.max_anchor_set_bytes
        )
        backend = pipeline.describe()
        self.grids = (
            GridOutputs(settings.grids, len(self.anchor_switch.head().anchor_set), settings.instance, settings.risk)
            if settings.grids
            else None
        )
        grids = self.grids
        self.reuse = ReuseTracker(
            settings.reuse,
            settings.schedule,
            grids.pose_of if grids else lambda source: None,
            anchors_version=lambda: self.anchor_switch.head().version,
        )
        self.queue: LatestFrameQueue[PendingFrame] = LatestFrameQueue(
            round(settings.pending_budget_mb * 1e6),
            policy=policy_for(settings.schedule, self.reuse.motion),
            triage=settings.reuse.enabled or settings.schedule.policy == "need",
        )
        self.ros_graph = RosGraph(session, settings, self.stats.rejected) if settings.ros_inputs else None
        self.outputs = FrameOutputs(session, self.keys, self.ros_graph)
        self.freshness = Freshness.from_settings(settings, log)  # the one judge of a frame's age
        ledger = CreditLedger(settings.instance, backend.input_size, self.freshness.max_age_s)
        self.credits = CreditPublisher(session, self.keys, ledger, self.stats)
        # the one hand-off out: encoded in the runtime, put by self.outputs, the credits told
        self.publisher = FramePublisher(OutputBuilder(settings, backend.model_id), self.outputs, self.credits.published)
        forget = (
            self.queue.forget,
            self.history.forget,
            self.stats.forget,
            self.outputs.forget,
            self.publisher.forget,
            self.credits.forget,
            self.freshness.offsets.forget,
            self.reuse.forget,
        )
        self.sources = SourceTracker(
            settings.max_sources, settings.source_idle_s, forget, reclaim_after_s=settings.reclaim_after_s
        )
        self.admission = Admission(settings, self.sources, self.queue, self.stats, self.credits.freed, self.freshness)
        idle = min(settings.source_idle_s, TABLE_IDLE_S)  # the table's memory, not the source's state
        self.assignment = Assignment(idle_s=idle, max_known=4 * settings.max_sources)
        self.progress = ProgressMonitor(settings.stall_after_s)
        self.status_parts = StatusParts(
            settings.instance,
            time.time(),
            pipeline,
            self.anchor_switch,
            self.queue,
            self.history,
            self.stats,
            self.sources,
            self.progress,
            self.freshness.offsets,
        )
        gate = FrameGate(self.owns, self.freshness)
        self.worker = FrameWorker(
            self.queue,
            pipeline,
            self.history,
            self.stats,
            self.sources,
            settings,
            self.publisher,
            self.credits.taken,
            self.progress,
            gate,
            self.admission,
            Triage(self.queue, self.reuse, settings, self.stats, self.publisher.republish, self.credits.answered)
            if self.queue.triage
            else None,
            grids=self.grids,
        )
        self._watchdog = threading.Thread(target=self._watch_progress, name="gcdtrav-watchdog", daemon=True)
        self._check_inputs()
        self.experience = experience_bus(session, settings, pipeline, self.grids, self.stats, self.owns)

    def _check_inputs(self) -> None:
        own = zenoh.KeyExpr(self.keys.outputs)
        for expression in self.settings.inputs:
            try:
                key = zenoh.KeyExpr(expression)
            except zenoh.ZError as err:
                raise SettingsError(f"input '{expression}' is not a valid key expression: {err}") from None
            if key.intersects(own):
                raise SettingsError(
                    f"input '{expression}' overlaps the service's outputs '{self.keys.outputs}' (maps would "
                    f"feed back as inputs); subscribe to narrower keys, e.g. '{self.prefix}/in/**'"
                )

    # ---- lifecycle -----------------------------------------------------------------------------------
    def start(self, observe_s: float = 0.0) -> None:
        """Serve. The instance watches the others and notes the sources on the inputs from the start, but
        joins the fleet (declares its token, so sources move to it) only once it serves: subscribers and
        worker up, and after ``observe_s`` of watching, so that its table already holds the robots the others
        serve (a robot it has not seen twice yet would be claimed by neither). Its queryables come last: an
        instance that answers status serves."""
        began = time.monotonic()
        if self.settings.health_port:  # first: a supervisor sees it starting
            self.probes = Probes(self.liveness, self.readiness, self.settings.health_address, self.settings.health_port)
            self.probes.start()
        self.membership = Membership(
            self.session, self.prefix, self.settings.instance, assignment=self.assignment, join=False
        )
        self.anchor_sync = AnchorSync(self.session, self.keys, self.settings.instance, self.anchor_switch)
        for expression in self.settings.inputs:
            head = literal_head(expression)
            self._declared.append(self.session.declare_subscriber(expression, self._image_handler(head)))
        for ros_input in self.settings.ros_inputs:
            self._declared.append(self.session.declare_subscriber(ros_input.key, self._ros_handler(ros_input)))
        if self.ros_graph is not None:
            self.ros_graph.start()
        if self.grids is not None:
            self._declare_grid_inputs(self.grids)
        if self.experience is not None:
            self._declared += self.experience.start()
        self.worker.start()
        self._watchdog.start()
        self._stopping.wait(max(0.0, began + observe_s - time.monotonic()))
        self.membership.rejoin()
        self._declare_queryables()  # answering status means serving: callers wait for it
        backend, active = self.pipeline.describe(), self.anchor_switch.head().anchor_set
        log.info(
            "serving: inputs %s, ROS inputs %s, outputs %s/out/{source}/maps, grids %s, experience %s, model %s (%s), "
            "anchor set %s (%d anchors), method %s, outputs %s",
            self.settings.inputs,
            [r.key for r in self.settings.ros_inputs],
            self.prefix,
            grids_described(self.settings.grids),
            self.experience.reads() if self.experience is not None else "off",
            backend.model_id,
            backend.precision,
            active.version,
            len(active),
            self.pipeline.settings.method.value,
            "overlapping inference" if self.worker.overlap_outputs else "after inference, same thread",
        )

    def stop(self, timeout: float | None = None) -> None:
        """Leave the fleet first (the token goes: the others take this instance's sources on their next frame),
        stop taking frames, finish and publish the frame in flight, undeclare everything; within ``timeout``
        (default ``shutdown_grace_s``). The frames still queued are counted dropped (``shutdown``): their
        robots' next frames go to the new owners."""
        timeout = self.settings.shutdown_grace_s if timeout is None else timeout
        deadline = time.monotonic() + timeout
        self._stopping.set()
        if self.membership is not None:
            self._leaving = self.membership.leave()
        self.queue.close()
        if not self.worker.stop(deadline):
            log.warning("the frame in flight did not finish within %.1f s; its outputs are dropped", timeout)
        if self.membership is not None:
            self.membership.close()
        if self.probes is not None:
            self.probes.close()
        self.outputs.close()  # before the session's entities: a late frame is refused, not put on a dead key
        self.credits.close()
        undeclare_all(self._declared)
        if self.experience is not None:
            self.experience.close()  # after its subscribers: the last outcomes are saved too
        self._declared.clear()
        if self.anchor_sync is not None:
            self.anchor_sync.close()
        self.anchor_switch.close()
        if self.ros_graph is not None:
            self.ros_graph.close()

    # ---- input ---------------------------------------------------------------------------------------
    def _image_handler(self, head: str) -> Callable[[zenoh.Sample], None]:
        return lambda sample: self._on_image(sample, head)

    def _on_image(self, sample: zenoh.Sample, head: str) -> None:
        """Runs on zenoh's thread: only rate-check, size-check and enqueue; decoding happens in the worker."""
        if self._stopping.is_set():
            return
        key = str(sample.key_expr)
        if self.keys.input_message(key) is not None:  # an outcome or an answer: never an image, nor its intake
            if self.experience is None:
                self.stats.rejected(None, "experience_off", f"{key}: experience is not enabled on this service")
            return
        if not self._admitted(publisher := publisher_of(sample)):
            return
        self._enqueue(input_source_of(key, head), sample, None, publisher)

    def _admitted(self, publisher: str | None) -> bool:
        """The publisher is within its intake rate: checked before anything else of the sample is read."""
        if self.intake_rate.admit(publisher):
            return True
        self.stats.rejected_unread("rate_limited", lambda: f"publisher {publisher or '(no source info)'}")
        return False

    def _ros_handler(self, ros_input: RosInput) -> Callable[[zenoh.Sample], None]:
        return lambda sample: self._on_ros_image(sample, ros_input)

    def _on_ros_image(self, sample: zenoh.Sample, ros_input: RosInput) -> None:
        if self._stopping.is_set() or not self._admitted(publisher := publisher_of(sample)):
            return
        key = str(sample.key_expr)
        try:
            topic = ros_io.parse_key(key, ros_input.layout, ros_input.zenoh_namespace)
        except RejectedInput as err:
            self.stats.rejected(None, err.reason, f"{key}: {err.detail}")  # not a source: keys are unbounded
            return
        if ros_io.is_output_topic(topic.topic, self.settings.ros_output.topic_templates()):
            return  # ROS outputs of a gcdtrav service, matched by a wide input expression
        if ros_input.message_type != "auto":
            topic = replace(topic, msgtype=ros_input.message_type)
        self._enqueue(topic.source, sample, topic, publisher)

    def owns(self, source: str) -> bool:
        """Instances of one prefix share the sources; before start() this instance owns them all; leaving,
        those it owned when it left (only the frames already in its hands are finished)."""
        if self._leaving is not None:
            return self._leaving(source)
        return self.membership is None or self.membership.owns(source)

    def liveness(self) -> Health:
        """The worker progresses (the /livez probe)."""
        return self.progress.health()

    def readiness(self) -> Health:
        """In the fleet and serving (the /readyz probe)."""
        if self._stopping.is_set():
            return Health(False, "draining: left the fleet, finishing the frame in flight")
        health = self.progress.health()
        if not health.healthy:
            return health
        if self.membership is None or self.membership.withdrawn:
            return Health(False, "starting: not in the fleet yet")
        return health

    def _watch_progress(self) -> None:
        """Withdraw from the fleet while the worker is stalled, rejoin when it progresses again."""
        while not self._stopping.wait(WATCHDOG_INTERVAL_S):
            change = self.progress.check(len(self.queue))
            if change is None or self.membership is None:
                continue
            if change.health.healthy:
                log.warning("worker %s: rejoining the fleet", change.health.reason)
                self.membership.rejoin()
            else:
                log.error("worker %s: withdrawing from the fleet (its sources fail over)", change.health.reason)
                self.membership.withdraw()

    def _enqueue(self, source: str, sample: zenoh.Sample, ros: ros_io.RosTopic | None, publisher: str | None) -> None:
        if self.membership is not None:
            self.membership.note(source)
        if self.owns(source):  # else another live instance serves this source
            key, size, encoding = str(sample.key_expr), len(sample.payload), str(sample.encoding)
            self.admission.offer(source, key, size, sample.payload.to_bytes, encoding, ros, publisher)

    def _declare_queryables(self) -> None:
        per_source = SourceQueries(self.keys, self.history, self.grids, self.owns, self.settings.risk)
        anchors = AnchorQueries(self.keys, self.anchor_switch, self.stats)
        handlers = [(self.keys.patch("**"), per_source.on_patch, False)]
        if self.grids is not None:
            handlers.append((self.keys.cell("**"), per_source.on_cell, False))
        handlers += [
            (self.keys.anchors, anchors.on_anchors, True),
            (self.keys.anchor_history, anchors.on_history, True),
            (self.keys.anchor_rollback, anchors.on_rollback, True),
            (self.keys.status, self._on_status_query, True),
        ]
        for key, handler, complete in handlers:
            self._declared.append(
                self.session.declare_queryable(key, answering(handler, self.stats), complete=complete)
            )

    def _declare_grid_inputs(self, grids: GridOutputs) -> None:
        for key, source, setter, reason in grids.inputs():  # poses by grid, CameraInfo and depth by camera
            handler = self._grid_input_handler(source, setter, reason)
            self._declared.append(self.session.declare_subscriber(key, handler))

    def _grid_input_handler(
        self, source: str, setter: Callable[[str, bytes], None], reason: str
    ) -> Callable[[zenoh.Sample], None]:
        def handle(sample: zenoh.Sample) -> None:
            try:
                setter(source, sample.payload.to_bytes())
            except (MessageError, ValueError) as err:
                self.stats.rejected(source, reason, str(err)[:200])

        return handle

    def status(self) -> ServiceStatus:
        live = sorted(self.membership.live()) if self.membership else None
        fleet = self.anchor_sync.fleet.versions() if self.anchor_sync else {}
        experience = self.experience.status() if self.experience is not None else None
        return self.status_parts.status(time.time(), live, fleet, experience)

    def _on_status_query(self, query: zenoh.Query) -> None:
        replies.check_no_parameters(query)
        replies.reply(query, self.keys.status, self.status())
