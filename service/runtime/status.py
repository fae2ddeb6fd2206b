"""The service's status, assembled from the runtime's parts; the bus only answers the query with it."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from gcdtrav.schemas.messages import ExperienceStatus, ServiceStatus, StoreStatus
from gcdtrav.service.pipeline import Pipeline
from gcdtrav.service.runtime.fleet.anchor_switch import AnchorSwitch
from gcdtrav.service.runtime.fleet.fleet_models import FleetModelsStatus
from gcdtrav.service.runtime.grids import GridOutputs
from gcdtrav.service.runtime.history import FrameHistory
from gcdtrav.service.runtime.intake.clock_offset import ClockOffsets
from gcdtrav.service.runtime.intake.sources import SourceTracker
from gcdtrav.service.runtime.progress import ProgressMonitor
from gcdtrav.service.runtime.schedule.latest_queue import LatestFrameQueue
from gcdtrav.service.runtime.stats import ServiceStats


@dataclass(frozen=True)
class StatusParts:
    """The runtime objects a status reads, each the owner of what it contributes."""

    instance: str
    started_at: float  # wall-clock seconds
    pipeline: Pipeline  # the backend's description, the method
    anchors: AnchorSwitch  # the active set and when it was accepted
    queue: LatestFrameQueue[Any]
    history: FrameHistory
    stats: ServiceStats
    sources: SourceTracker
    progress: ProgressMonitor
    clock_offsets: ClockOffsets  # each source's clock against this instance's, as estimated
    grids: GridOutputs | None = None  # the ground grids, if any: their health

    def status(
        self,
        now: float,
        live: list[str] | None = None,
        fleet: Mapping[str, str] | None = None,
        experience: ExperienceStatus | None = None,
        models: FleetModelsStatus | None = None,
        store: StoreStatus | None = None,
    ) -> ServiceStatus:
        """This instance's status at ``now``; ``live``: the instances of the prefix (None: this one alone);
        ``fleet``: every instance's anchor-set version as this one knows it; ``experience``: its own status
        (service/experience, a layer above the runtime), None when off."""
        counts = self.stats.snapshot(self.queue.counters(), self.clock_offsets.offsets(), self.queue.policy.shares())
        health = self.progress.health()
        head = self.anchors.head()
        backend = self.pipeline.describe()
        return ServiceStatus(
            instance=self.instance,
            instances=sorted(live) if live is not None else [self.instance],
            uptime_s=now - self.started_at,
            model=backend.model_id,
            anchor_set_version=head.version,
            method=self.pipeline.settings.method,
            precision=backend.precision,
            precision_reason=backend.precision_reason,
            measuring=backend.measuring,
            queued=len(self.queue),
            queued_bytes=self.queue.nbytes,
            sources=counts.sources,
            rejected_by_reason=counts.rejected_by_reason,
            dropped_by_reason=counts.dropped_by_reason,
            last_errors=counts.last_errors,
            history_bytes=self.history.nbytes,
            history_budget_bytes=self.history.budget_bytes or 0,
            tracked_sources=len(self.sources),
            max_sources=self.sources.max_sources,
            healthy=health.healthy,
            reason=health.reason,
            anchor_set_accepted_at=head.accepted_at or None,  # 0: the set it started with, never swapped
            anchor_sets=dict(fleet or {}),
            experience=experience,
            store=store,
            grids=self.grids.statuses(self.clock_offsets.offsets()) if self.grids is not None else None,
            model_fingerprint=backend.fingerprint,
            model_refused=models.refused if models else "",
            instance_models=dict(models.fingerprints) if models else {},
        )
