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
from functools import partial
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
from gcdtrav.service.bus.fleet_models import FleetModels
from gcdtrav.service.bus.guard import answering
from gcdtrav.service.bus.membership import Membership
from gcdtrav.service.bus.outputs import FrameOutputs
from gcdtrav.service.bus.presence import declare_relay_health
from gcdtrav.service.bus.queryables import AnchorQueries, SourceQueries
from gcdtrav.service.bus.ros_graph import RosGraph, graph_inputs
from gcdtrav.service.bus.tf import declare_tf_inputs
from gcdtrav.service.experience.service import service_experience
from gcdtrav.service.pipeline import Pipeline
from gcdtrav.service.ros import cdr as ros_io
from gcdtrav.service.runtime.assembly import Runtime
from gcdtrav.service.runtime.fleet.state_lock import StateLock
from gcdtrav.service.runtime.metrics import MetricsSources, ServiceMetrics
from gcdtrav.service.runtime.progress import Health
from gcdtrav.service.runtime.stats import ServiceStats
from gcdtrav.service.store import Store, StoreError, StoreUnavailable
from gcdtrav.service.store.opening import service_outbox
from gcdtrav.service.store.outbox import PairOutbox, store_status

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
    def __init__(
        self, session: zenoh.Session, pipeline: Pipeline, settings: ServiceSettings, store: Store | None = None
    ) -> None:
        """``store``: the fleet's store, opened by `gcdtrav serve` (service/store); None: the outbox opens the one
        ``settings.store`` names."""
        self.session, self.pipeline, self.settings = session, pipeline, settings
        self.prefix, self.keys = settings.prefix, Keys(settings.prefix)
        self.metrics = ServiceMetrics(settings.instance)  # its histograms see every frame the stats count
        self.stats = ServiceStats(log, settings.source_idle_s, self.metrics.timings)  # the bus's refusals too
        self._declared: list[Any] = []
        self._stopping = threading.Event()
        self.membership: Membership | None = None
        self._leaving: Callable[[str], bool] | None = None  # after stop(): what it owned when it left
        self.anchor_sync: AnchorSync | None = None
        self.ros_graph = RosGraph(session, settings, self.stats.rejected) if graph_inputs(settings) else None
        self.outputs = FrameOutputs(session, self.keys, self.ros_graph)  # the runtime's sinks: they only put
        self.credits = CreditPublisher(session, self.keys)
        self.store = self._locked_outbox(store)
        experience = service_experience(settings, self.stats.rejected, self.store)  # None when off; asks at fusion
        asks = experience.after_fusion if experience is not None else None
        build = (settings, pipeline, self.outputs, self.credits, self.owns, self._open_store, self.stats, time.time())
        self.runtime = Runtime.build(*build, after_fusion=asks)
        self._watchdog = threading.Thread(target=self._watch_progress, name="gcdtrav-watchdog", daemon=True)
        self._check_inputs()
        switch = self.runtime.anchor_switch  # proposals are judged against its history and kept in its store
        self.experience = experience_bus(session, settings, experience, self.stats, self.owns, switch)
        self._collect_metrics()

    def _locked_outbox(self, store: Store | None) -> PairOutbox:
        """The state dir locked for this instance, and the outbox to the store of pairs and anchor history:
        reachable or not, the service serves; refused (SettingsError), no start and the lock released."""
        self.state_lock = StateLock(self.settings.state_file, self.settings.instance)  # one service per state file
        try:
            return service_outbox(self.settings, store)
        except StoreError as err:
            self.state_lock.release()
            raise SettingsError(str(err)) from None

    def _collect_metrics(self) -> None:
        calibration = self.experience.calibration if self.experience is not None else None
        heard = self.runtime.presence.heard  # the robots heard: the silent-robot alert's series
        sources = MetricsSources(self.status, self._owned, self.settings.max_frame_age_s, calibration, heard)
        self.metrics.collect(sources)

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
        instance that answers status serves. The anchor set's token comes before the alive token: a join is
        logged with it (membership.describe)."""
        began = time.monotonic()
        self.anchor_sync = AnchorSync(self.session, self.keys, self.settings.instance, self.runtime.anchor_switch)
        models = FleetModels(
            self.session,
            self.keys,
            self.settings.instance,
            self.pipeline.describe().fingerprint,
            self.settings.allow_mixed_models,
        )
        fleet = self.anchor_sync.fleet
        self.membership = Membership(
            self.session,
            self.prefix,
            self.settings.instance,
            assignment=self.runtime.assignment,
            models=models,
            anchor_set_of=lambda instance: fleet.versions().get(instance),
            join=False,
        )
        for expression in self.settings.inputs:
            head = literal_head(expression)
            self._declared.append(self.session.declare_subscriber(expression, partial(self._on_image, head=head)))
        for ros_input in self.settings.ros_inputs:
            handler = partial(self._on_ros_image, ros_input=ros_input)
            self._declared.append(self.session.declare_subscriber(ros_input.key, handler))
        if self.ros_graph is not None:
            self.ros_graph.start()
        self._declare_grid_inputs()
        self.store.start()
        self._declared.append(declare_relay_health(self.session, self.keys, self.runtime.presence, self.stats))
        if self.experience is not None:
            self._declared += self.experience.start()
        self.runtime.worker.start()
        self._watchdog.start()
        self._stopping.wait(max(0.0, began + observe_s - time.monotonic()))
        self.membership.rejoin()
        self._declare_queryables()  # answering status means serving: callers wait for it
        backend, active = self.pipeline.describe(), self.runtime.anchor_switch.head().anchor_set
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
            "overlapping inference" if self.runtime.worker.overlap_outputs else "after inference, same thread",
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
        self.runtime.queue.close()
        if not self.runtime.worker.stop(deadline):
            log.warning("the frame in flight did not finish within %.1f s; its outputs are dropped", timeout)
        if self.membership is not None:
            self.membership.close()
        self.runtime.publish_safe_speed(stale_only=False)  # no mask outlives the service: the last frame is out
        self.outputs.close()  # before the session's entities: a late frame is refused, not put on a dead key
        self.credits.close()
        undeclare_all(self._declared)
        if self.experience is not None:
            self.experience.close()  # after its subscribers: the last outcomes are saved too
        self.store.close()  # what is queued is written while the store takes it (bounded), then closed
        self._declared.clear()
        if self.anchor_sync is not None:
            self.anchor_sync.close()
        self.runtime.anchor_switch.close()
        self.state_lock.release()
        if self.ros_graph is not None:
            self.ros_graph.close()

    # ---- input ---------------------------------------------------------------------------------------
    def _on_image(self, sample: zenoh.Sample, head: str) -> None:
        """Runs on zenoh's thread: only rate-check, size-check and enqueue; decoding happens in the worker."""
        if self._stopping.is_set():
            return
        key = str(sample.key_expr)
        if self.keys.input_message(key) is not None:  # an outcome or an answer: never an image, nor its intake
            if self.experience is None:
                self.stats.rejected(None, "experience_off", f"{key}: experience is not enabled on this service")
            return
        if not self.runtime.admission.admit(publisher := publisher_of(sample)):
            return
        self._enqueue(input_source_of(key, head), sample, None, publisher)

    def _on_ros_image(self, sample: zenoh.Sample, ros_input: RosInput) -> None:
        if self._stopping.is_set() or not self.runtime.admission.admit(publisher := publisher_of(sample)):
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

    def _owned(self) -> int:
        """Sources the fleet's table gives this instance; before start() it owns what it tracks."""
        return self.membership.owned() if self.membership is not None else len(self.runtime.sources)

    def owns(self, source: str) -> bool:
        """Instances of one prefix share the sources; before start() this instance owns them all; leaving,
        those it owned when it left (only the frames already in its hands are finished)."""
        if self._leaving is not None:
            return self._leaving(source)
        return self.membership is None or self.membership.owns(source)

    def liveness(self) -> Health:
        """The worker progresses (the /livez probe)."""
        return self.runtime.progress.health()

    def readiness(self) -> Health:
        """In the fleet and serving (the /readyz probe)."""
        in_fleet = self.membership is not None and not self.membership.withdrawn
        return self.runtime.readiness(self._stopping.is_set(), in_fleet)

    def _open_store(self) -> Store:
        """The store, for the anchor switch; StoreUnavailable while it was never reached."""
        opened = self.store.store
        if opened is None:
            raise StoreUnavailable(f"the store {self.store.location} was not reached yet")
        return opened

    def _watch_progress(self) -> None:
        """Withdraw from the fleet while the worker is stalled, rejoin when it progresses again; serve the
        store's anchor set once a store away at start answers."""
        while not self._stopping.wait(WATCHDOG_INTERVAL_S):
            change = self.runtime.tick()
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
        self.runtime.presence.frame(source)
        if self.owns(source):  # else another live instance serves this source
            key, size, encoding = str(sample.key_expr), len(sample.payload), str(sample.encoding)
            self.runtime.admission.offer(source, key, size, sample.payload.to_bytes, encoding, ros, publisher)

    def _declare_queryables(self) -> None:
        per_source = SourceQueries(self.keys, self.runtime.history, self.runtime.grids, self.owns, self.settings.risk)
        anchors = AnchorQueries(self.keys, self.runtime.anchor_switch, self.stats)
        handlers = [(self.keys.patch("**"), per_source.on_patch, False)]
        if self.runtime.grids is not None:
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

    def _declare_grid_inputs(self) -> None:
        grids = self.runtime.grids
        if grids is None:
            return
        for key, source, setter, reason in grids.inputs():  # poses by grid, CameraInfo and depth by camera
            handler = partial(self._on_grid_input, source, setter, reason)
            self._declared.append(self.session.declare_subscriber(key, handler))
        self._declared += declare_tf_inputs(self.session, grids, self.stats)  # mounts and poses from tf

    def _on_grid_input(
        self, source: str, setter: Callable[[str, bytes], None], reason: str, sample: zenoh.Sample
    ) -> None:
        try:
            setter(source, sample.payload.to_bytes())
        except (MessageError, ValueError) as err:
            self.stats.rejected(source, reason, str(err)[:200])

    def status(self) -> ServiceStatus:
        live = sorted(self.membership.live()) if self.membership else None
        fleet = self.anchor_sync.fleet.versions() if self.anchor_sync else {}
        experience = self.experience.status() if self.experience is not None else None
        models = self.membership.models if self.membership else None
        models_status = models.status(live or []) if models is not None else None
        store = store_status(self.store.state())
        return self.runtime.status_parts.status(time.time(), live, fleet, experience, models_status, store)

    def _on_status_query(self, query: zenoh.Query) -> None:
        replies.check_no_parameters(query)
        replies.reply(query, self.keys.status, self.status())
