"""The zenoh-free runtime assembled in one place: ``Runtime.build`` makes every part and hands each the others
it needs, so the service (service/bus/node.py wires zenoh to it) and the tests run the same assembly.

What the bus provides: where a frame's payloads go (``sink``, service/bus/outputs.py), where the credits go
(``credit_sink``, service/bus/credits.py) and whether this instance owns a source (``owns``, the fleet's
membership). What it calls: ``admission`` from its subscribers (``admit``, then ``offer``), the parts the
queryables answer from (``history``, ``grids``, ``anchor_switch``), ``status_parts`` for the status query,
``assignment`` for the membership and ``worker`` to start and stop.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.pipeline import Pipeline
from gcdtrav.service.runtime.fleet.anchor_switch import AnchorSwitch
from gcdtrav.service.runtime.fleet.assignment import TABLE_IDLE_S, Assignment
from gcdtrav.service.runtime.fleet.credits import CreditLedger, Credits, CreditSink
from gcdtrav.service.runtime.frames import PendingFrame
from gcdtrav.service.runtime.grids import GridOutputs
from gcdtrav.service.runtime.grids.outputs import AfterFusion
from gcdtrav.service.runtime.history import FrameHistory
from gcdtrav.service.runtime.http_endpoints import ready
from gcdtrav.service.runtime.intake.admission import Admission
from gcdtrav.service.runtime.intake.freshness import FrameGate, Freshness
from gcdtrav.service.runtime.intake.presence import SourcePresence
from gcdtrav.service.runtime.intake.sources import SourceTracker
from gcdtrav.service.runtime.outputs import FramePublisher, OutputBuilder, OutputSink
from gcdtrav.service.runtime.progress import Change, Health, ProgressMonitor
from gcdtrav.service.runtime.schedule.latest_queue import LatestFrameQueue
from gcdtrav.service.runtime.schedule.share import policy_for
from gcdtrav.service.runtime.stats import ServiceStats
from gcdtrav.service.runtime.status import StatusParts
from gcdtrav.service.runtime.triage.reuse import ReuseTracker, Triage
from gcdtrav.service.runtime.worker import FrameWorker
from gcdtrav.service.store import Store

log = logging.getLogger("gcdtrav.service")


class Sink(OutputSink, Protocol):
    """The outputs' sink, which also forgets a source's publishers when the source goes."""

    def forget(self, source: str) -> None: ...


@dataclass(frozen=True)
class Runtime:
    """Every part of the runtime, as ``build`` wired them."""

    settings: ServiceSettings
    pipeline: Pipeline
    stats: ServiceStats
    history: FrameHistory
    anchor_switch: AnchorSwitch  # over the fleet's store: the anchor history and the active set
    grids: GridOutputs | None
    reuse: ReuseTracker
    queue: LatestFrameQueue[PendingFrame]
    freshness: Freshness  # the one judge of a frame's age
    credits: Credits
    publisher: FramePublisher  # the one hand-off out
    sources: SourceTracker
    admission: Admission
    assignment: Assignment
    progress: ProgressMonitor
    status_parts: StatusParts
    worker: FrameWorker
    presence: SourcePresence  # the robots heard: the silent-robot alert's metrics

    @classmethod
    def build(
        cls,
        settings: ServiceSettings,
        pipeline: Pipeline,
        sink: Sink,
        credit_sink: CreditSink,
        owns: Callable[[str], bool],
        store: Store | Callable[[], Store],
        stats: ServiceStats | None = None,
        started_at: float | None = None,
        clock: Callable[[], float] = time.monotonic,
        after_fusion: AfterFusion | None = None,
    ) -> Runtime:
        """The runtime of ``settings``; ``stats``: shared with the bus (its refusals are counted there too);
        ``started_at``: wall-clock seconds, for the status's uptime (None: now); ``clock``: the sources'
        idleness is timed by it (monotonic seconds); ``after_fusion``: the experience's, called by the grids
        under their lock (``Experience.after_fusion``: its question leaves with the frame's outputs); ``store``: the
        fleet's store, or what returns it once open (the service's outbox: the store is opened in one place)."""
        stats = stats or ServiceStats(log, settings.source_idle_s)
        history = FrameHistory(settings.history, round(settings.history_budget_mb * 1e6))
        switch = AnchorSwitch(pipeline, store, settings.instance, settings.max_anchor_set_bytes)
        grids = (
            GridOutputs(
                settings.grids,
                len(switch.head().anchor_set),
                settings.instance,
                settings.risk,
                clock_mode=settings.clock,
                after_fusion=after_fusion,
            )
            if settings.grids
            else None
        )
        reuse, queue = _schedule(settings, grids, switch)
        freshness = Freshness.from_settings(settings, log)
        backend = pipeline.describe()
        credits = Credits(CreditLedger(settings.instance, backend.input_size, freshness.max_age_s), stats, credit_sink)
        # the one hand-off out: encoded here, put by the sink, the credits told
        unchanged = grids.unchanged if grids is not None else lambda source: None
        publisher = FramePublisher(OutputBuilder(settings, backend.model_id), sink, credits.published, unchanged)
        forget = (
            queue.forget,
            history.forget,
            stats.forget,
            sink.forget,
            publisher.forget,
            credits.forget,
            freshness.offsets.forget,
            reuse.forget,
        )
        sources = SourceTracker(
            settings.max_sources, settings.source_idle_s, forget, clock, reclaim_after_s=settings.reclaim_after_s
        )
        admission = Admission(settings, sources, queue, stats, credits.freed, freshness)
        progress = ProgressMonitor(settings.stall_after_s, clock)
        status_parts = StatusParts(
            settings.instance,
            time.time() if started_at is None else started_at,
            pipeline,
            switch,
            queue,
            history,
            stats,
            sources,
            progress,
            freshness.offsets,
            grids,
        )
        triage = Triage(queue, reuse, settings, stats, publisher.republish, credits.answered) if queue.triage else None
        worker = FrameWorker(
            queue,
            pipeline,
            history,
            stats,
            sources,
            settings,
            publisher,
            credits.taken,
            progress,
            FrameGate(owns, freshness),
            admission,
            triage,
            grids=grids,
        )
        idle = min(settings.source_idle_s, TABLE_IDLE_S)  # the table's memory, not the source's state
        assignment = Assignment(idle_s=idle, max_known=4 * settings.max_sources)
        return cls(
            settings,
            pipeline,
            stats,
            history,
            switch,
            grids,
            reuse,
            queue,
            freshness,
            credits,
            publisher,
            sources,
            admission,
            assignment,
            progress,
            status_parts,
            worker,
            SourcePresence(settings.max_sources, settings.source_idle_s),
        )

    # ---- the watchdog's jobs, zenoh-free (the bus's watchdog thread calls ``tick``) ------------------------
    def tick(self) -> Change | None:
        """Every WATCHDOG_INTERVAL_S: serve the store's anchor set once a store away at start answers, replace
        the live speed mask of every grid gone stale with the safe one, and check the worker's progress; the
        change of health, if any (the bus withdraws from the fleet or rejoins on it)."""
        self.anchor_switch.sync(_synced)
        self.publish_safe_speed(stale_only=True)
        return self.progress.check(len(self.queue))

    def publish_safe_speed(self, stale_only: bool) -> None:
        """The safe speed mask (the floor everywhere) of every grid whose live mask went stale or, when the
        service stops, of every grid that has one (docs/grid.md, "Speed from uncertainty")."""
        if self.grids is not None:
            self.publisher.publish_speed(self.grids.safe_speed(stale_only))

    def readiness(self, draining: bool, in_fleet: bool) -> Health:
        """In the fleet and serving (the /readyz probe)."""
        return ready(self.progress.health(), draining, in_fleet)


def _synced(anchors: AnchorSet | None, error: BaseException | None) -> None:
    if error is not None:
        log.error("anchor set from the store: %s", error)


def _schedule(
    settings: ServiceSettings, grids: GridOutputs | None, switch: AnchorSwitch
) -> tuple[ReuseTracker, LatestFrameQueue[PendingFrame]]:
    """The reuse's tracker (poses from the grids) and the queue with the schedule's policy."""
    reuse = ReuseTracker(
        settings.reuse,
        settings.schedule,
        grids.reuse_pose if grids else lambda source, stamp, received_at: None,
        anchors_version=lambda: switch.head().version,
    )
    queue: LatestFrameQueue[PendingFrame] = LatestFrameQueue(
        round(settings.pending_budget_mb * 1e6),
        policy=policy_for(settings.schedule),
        triage=settings.reuse.enabled or settings.schedule.policy == "need",
    )
    return reuse, queue
