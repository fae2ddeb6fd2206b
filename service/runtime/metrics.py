"""The service's metrics in Prometheus's exposition format (docs/metrics.md). No middleware, no HTTP here: the
serve command serves ``ServiceMetrics.registry`` on ``metrics_port`` (http_endpoints.py).

Two kinds, by what their meaning needs:

- **Read at scrape time** (``StatusCollector``): every count and state the service already keeps for its
  status (``ServiceStats``, the queue, the membership, the backend's description) is read from the one
  ``ServiceStatus`` the status query answers with, so the metrics and ``gcdtrav status`` cannot disagree and
  nothing is counted twice on the hot path. A forgotten source leaves the status, and so its series go.
- **Observed at the event** (``FrameTimings``, the stats' ``FrameEvents``): distributions (inference time,
  queue wait, the maps' age when published) are histograms, which must see every value as it happens.

Labels are bounded: ``source`` takes at most ``max_sources`` tracked names plus the refused ones the status
lists (``stats.REFUSED_SOURCES``), and at most ``max_sources`` heard ones (``intake.presence``); ``reason`` is a
code of the service; no stamp or payload value is a label.

Every series carries ``gcdtrav_instance``, the instance's name (``InstanceLabel``): Prometheus's own
``instance`` is the scrape address, which a dashboard reader cannot tell apart from another pod's.
"""

from __future__ import annotations

import contextlib
import copy
import math
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

from gcdtrav.schemas.experience import CalibrationFigures
from gcdtrav.schemas.messages import GridStatus, ServiceStatus, SourceStatus, StoreStatus
from gcdtrav.service.runtime.intake.presence import Heard
from prometheus_client import CollectorRegistry, Histogram, disable_created_metrics
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, InfoMetricFamily, Metric
from prometheus_client.process_collector import ProcessCollector
from prometheus_client.registry import Collector

# Buckets, in seconds. Inference: a tiny model's milliseconds to a slow box's seconds. Age and wait: around
# the default max_frame_age_s (5 s) and schedule.max_wait_s (10 s), finer below 1 s where robots live.
INFERENCE_BUCKETS = (0.01, 0.025, 0.05, 0.1, 0.2, 0.35, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 5.0, 10.0)
AGE_BUCKETS = (0.05, 0.1, 0.2, 0.35, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 7.5, 10.0, 20.0)
WAIT_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0)
CALIBRATION_EVERY_S = 30.0  # the figures go over every stored pair: computed at most this often
INSTANCE_LABEL = "gcdtrav_instance"  # the instance's name, on every series (Prometheus's `instance` is the address)


class FrameTimings:
    """The histograms, observed at each event (``stats.FrameEvents``); thread-safe (prometheus_client's)."""

    def __init__(self, registry: CollectorRegistry) -> None:
        self.inference = Histogram(
            "gcdtrav_inference_seconds",
            "The backend's forward pass of one frame.",
            buckets=INFERENCE_BUCKETS,
            registry=registry,
        )
        self.queue_wait = Histogram(
            "gcdtrav_queue_wait_seconds",
            "From a frame's receipt to the worker taking it for inference.",
            buckets=WAIT_BUCKETS,
            registry=registry,
        )
        self.map_age = Histogram(
            "gcdtrav_map_age_seconds",
            "A source's maps when published (inferred or reused): their frame's age as max_frame_age_s judges it.",
            ["source"],
            buckets=AGE_BUCKETS,
            registry=registry,
        )

    def waited(self, wait_s: float) -> None:
        self.queue_wait.observe(wait_s)

    def inferred(self, inference_s: float) -> None:
        self.inference.observe(inference_s)

    def published(self, source: str, map_age_s: float) -> None:
        self.map_age.labels(source).observe(map_age_s)

    def forget(self, source: str) -> None:
        with contextlib.suppress(KeyError):  # older prometheus_client raise for a series never observed
            self.map_age.remove(source)


@dataclass(frozen=True)
class MetricsSources:
    """What the collector reads at scrape time, each from its owner."""

    status: Callable[[], ServiceStatus]  # the status query's answer (service/runtime/status.py)
    owned: Callable[[], int]  # sources this instance serves in the fleet's table (service/runtime/fleet/assignment.py)
    max_frame_age_s: float | None  # the freshness limit the map-age alert compares with
    calibration: Callable[[], CalibrationFigures | None] | None = None  # None: experience off
    heard: Callable[[], dict[str, Heard]] = dict  # the robots heard (intake/presence.py); none by default


# What each metric read at scrape time means (docs/metrics.md says it at length, with units).
HELP = {
    "gcdtrav_frames_received": "Frames of a source that reached this instance.",
    "gcdtrav_frames_processed": "Frames inferred and published as maps.",
    "gcdtrav_frames_reused": "Frames not inferred (the view had not changed): the last maps published again.",
    "gcdtrav_frames_dropped": "Good frames never published, by reason (replaced, stale, not_owner, shutdown, ...).",
    "gcdtrav_frames_rejected": "Bad frames of a source, by reason (undecodable, oversized, bad_stamp, ...).",
    "gcdtrav_clock_offset_seconds": "Service clock minus the source's clock plus the link's smallest delay.",
    "gcdtrav_source_last_frame_timestamp_seconds": "When the source's last frame reached this instance (or its "
    "relay first spoke, before any frame), Unix seconds: the silent-robot alert compares it with now.",
    "gcdtrav_source_parked": "1 while the source's relay says its camera is stopped on purpose, else 0.",
    "gcdtrav_inputs_rejected": "Every rejected input by reason, those without a source too (rate_limited, ...).",
    "gcdtrav_healthy": "1 while the worker progresses, 0 while stalled (withdrawn from the fleet).",
    "gcdtrav_sources_owned": "Sources the fleet's table gives this instance (sums to the fleet's sources).",
    "gcdtrav_sources_tracked": "Sources this instance keeps state for.",
    "gcdtrav_sources_max": "The limit of tracked sources (max_sources).",
    "gcdtrav_instances_live": "Live instances of the prefix as this one sees them, itself included.",
    "gcdtrav_queued_frames": "Frames waiting for a glance or inference.",
    "gcdtrav_queued_bytes": "Their payload bytes (at most pending_budget_mb).",
    "gcdtrav_history_bytes": "Bytes of weights kept for patch queries.",
    "gcdtrav_measuring": "1 while precision auto times the modes in the background.",
    "gcdtrav_max_frame_age_seconds": "The freshness limit max_frame_age_s.",
    "gcdtrav_service": "What this instance runs: its name, model, precision mode, method, anchor set version.",
    "gcdtrav_experience_pairs": "Stored experience pairs in the store, the fleet's (every concept tuple).",
    "gcdtrav_store_reachable": "1 while this instance can reach and write its store of pairs and anchor history.",
    "gcdtrav_store_unreachable_since_seconds": "Since when the store is unreachable, s since the epoch (0: it is).",
    "gcdtrav_store_pending_pairs": "Pairs waiting in memory for the store (at most store.outbox_pairs).",
    "gcdtrav_store_written_pairs": "Pairs this instance wrote to the store.",
    "gcdtrav_store_dropped_pairs": "Pairs dropped: the store was unreachable and the outbox full.",
    "gcdtrav_calibration_pairs": "Experience pairs of the active concept tuple the calibration figures grade.",
    "gcdtrav_calibration_ece": "Expected calibration error of P(T < tau) (0: calibrated).",
    "gcdtrav_calibration_mae": "Mean |T - outcome| over the pairs.",
    "gcdtrav_calibration_coverage": "Share of outcomes at or above the alpha quantile of T (calibrated: 1 - alpha).",
    "gcdtrav_grid_speed_age_seconds": "Seconds since a grid's last speed filter mask went out (grids with speed).",
    "gcdtrav_grid_speed_safe": "1 while a grid's last speed mask is the safe one (the floor: stale or stopping).",
}


class StatusCollector(Collector):
    """Every count and state of the status, as metric families, read when Prometheus scrapes."""

    def __init__(self, sources: MetricsSources) -> None:
        self.sources = sources
        compute = sources.calibration
        self._calibration = ThrottledCalibration(compute) if compute is not None else None

    def describe(self) -> Iterable[Metric]:
        return []  # nothing collected at registration: the status is read at scrape time only

    def collect(self) -> Iterator[Metric]:
        status = self.sources.status()
        yield from source_families(status.sources)
        yield from heard_families(self.sources.heard())
        yield from service_families(status, self.sources.owned(), self.sources.max_frame_age_s)
        yield from speed_families(status.grids or [])
        if status.experience is not None:
            yield gauge("gcdtrav_experience_pairs", status.experience.pairs)
        if status.store is not None:
            yield from store_families(status.store)
        if self._calibration is not None:
            yield from calibration_families(self._calibration.figures())


def gauge(name: str, value: float) -> GaugeMetricFamily:
    return GaugeMetricFamily(name, HELP[name], value=value)


def source_families(sources: dict[str, SourceStatus]) -> Iterator[Metric]:
    """Per source (and reason): the frames' counts and the learnt clock offset."""
    received, processed, reused = (
        CounterMetricFamily(name, HELP[name], labels=["source"])
        for name in ("gcdtrav_frames_received", "gcdtrav_frames_processed", "gcdtrav_frames_reused")
    )
    dropped, rejected = (
        CounterMetricFamily(name, HELP[name], labels=["source", "reason"])
        for name in ("gcdtrav_frames_dropped", "gcdtrav_frames_rejected")
    )
    offset = GaugeMetricFamily("gcdtrav_clock_offset_seconds", HELP["gcdtrav_clock_offset_seconds"], labels=["source"])
    for name, source in sources.items():
        received.add_metric([name], source.received)
        processed.add_metric([name], source.processed)
        reused.add_metric([name], source.unchanged)
        for reason, count in sorted(source.dropped_by_reason.items()):
            dropped.add_metric([name, reason], count)
        for reason, count in sorted(source.rejected_by_reason.items()):
            rejected.add_metric([name, reason], count)
        if source.clock_offset_s is not None:
            offset.add_metric([name], source.clock_offset_s)
    yield from (received, processed, reused, dropped, rejected, offset)


def speed_families(grids: list[GridStatus]) -> Iterator[Metric]:
    """Per grid with a speed layer (labelled by the source it is published under): its last mask's age and
    whether it is the safe one (docs/grid.md, "Speed from uncertainty")."""
    names = ("gcdtrav_grid_speed_age_seconds", "gcdtrav_grid_speed_safe")
    age, safe = (GaugeMetricFamily(name, HELP[name], labels=["source"]) for name in names)
    for grid in grids:
        if grid.speed_ago_s is not None:
            age.add_metric([grid.source], grid.speed_ago_s)
            safe.add_metric([grid.source], int(bool(grid.speed_safe)))
    yield from (age, safe)


def heard_families(heard: dict[str, Heard]) -> Iterator[Metric]:
    """Per source heard (frames on the inputs, owner or not, or its relay's health): when its last frame came,
    and whether its relay says it parked (only for sources whose relay spoke)."""
    last_frame, parked = (
        GaugeMetricFamily(name, HELP[name], labels=["source"])
        for name in ("gcdtrav_source_last_frame_timestamp_seconds", "gcdtrav_source_parked")
    )
    for name, source in sorted(heard.items()):
        last_frame.add_metric([name], source.last_frame_at)
        if source.parked is not None:
            parked.add_metric([name], int(source.parked))
    yield from (last_frame, parked)


def service_families(status: ServiceStatus, owned: int, max_frame_age_s: float | None) -> Iterator[Metric]:
    """The instance: its health, sources, queue, fleet and what it runs."""
    rejected = CounterMetricFamily("gcdtrav_inputs_rejected", HELP["gcdtrav_inputs_rejected"], labels=["reason"])
    for reason, count in sorted(status.rejected_by_reason.items()):
        rejected.add_metric([reason], count)
    yield rejected
    yield gauge("gcdtrav_healthy", int(status.healthy is not False))
    yield gauge("gcdtrav_sources_owned", owned)
    yield gauge("gcdtrav_sources_tracked", status.tracked_sources)
    yield gauge("gcdtrav_sources_max", status.max_sources)
    yield gauge("gcdtrav_instances_live", len(status.instances))
    yield gauge("gcdtrav_queued_frames", status.queued)
    yield gauge("gcdtrav_queued_bytes", status.queued_bytes)
    yield gauge("gcdtrav_history_bytes", status.history_bytes)
    yield gauge("gcdtrav_measuring", int(status.measuring))
    if max_frame_age_s is not None:
        yield gauge("gcdtrav_max_frame_age_seconds", max_frame_age_s)
    info = InfoMetricFamily("gcdtrav_service", HELP["gcdtrav_service"])
    running = {
        "name": status.instance,
        "model": status.model,
        "precision": status.precision,
        "method": status.method.value,
        "anchor_set_version": status.anchor_set_version,
    }
    info.add_metric([], running)
    yield info


def store_families(store: StoreStatus) -> Iterator[Metric]:
    """The store as this instance sees it: reachable or since when not, and the pairs on their way."""
    yield gauge("gcdtrav_store_reachable", int(store.reachable))
    yield gauge("gcdtrav_store_unreachable_since_seconds", store.unreachable_since or 0.0)
    yield gauge("gcdtrav_store_pending_pairs", store.pending_pairs)
    for name, value in (("gcdtrav_store_written_pairs", store.written_pairs),
                        ("gcdtrav_store_dropped_pairs", store.dropped_pairs)):  # fmt: skip
        yield CounterMetricFamily(name, HELP[name], value=value)


def calibration_families(figures: CalibrationFigures | None) -> Iterator[Metric]:
    """The active anchor set graded by the experience: ECE of P(T < tau), quantile coverage, MAE."""
    if figures is None:
        return
    yield gauge("gcdtrav_calibration_pairs", figures.pairs)
    for name, value in (("gcdtrav_calibration_ece", figures.ece), ("gcdtrav_calibration_mae", figures.mae)):
        if value is not None and math.isfinite(value):
            yield gauge(name, value)
    coverage = GaugeMetricFamily("gcdtrav_calibration_coverage", HELP["gcdtrav_calibration_coverage"], labels=["alpha"])
    for alpha, share in sorted(figures.coverage.items()):
        if share is not None and math.isfinite(share):
            coverage.add_metric([alpha], share)
    yield coverage


class ThrottledCalibration:
    """The figures go over every stored pair (up to experience.max_pairs): recomputed at most every
    CALIBRATION_EVERY_S, not at every scrape; without pairs yet (nothing to compute), at every scrape."""

    def __init__(self, compute: Callable[[], CalibrationFigures | None], clock: Callable[[], float] = time.monotonic):
        self._compute, self._clock = compute, clock
        self._lock = threading.Lock()
        self._at = -math.inf
        self._figures: CalibrationFigures | None = None

    def figures(self) -> CalibrationFigures | None:
        with self._lock:
            none_yet = self._figures is None or self._figures.pairs == 0  # cheap: asked again until pairs come
            if none_yet or self._clock() - self._at >= CALIBRATION_EVERY_S:
                self._figures, self._at = self._compute(), self._clock()
            return self._figures


class InstanceLabel(CollectorRegistry):
    """A registry whose every sample carries ``gcdtrav_instance``: a panel or an alert names the instance as
    ``gcdtrav status`` does, with no join on the info metric, and a pod's series keep their name when its
    address changes."""

    def __init__(self, instance: str) -> None:
        super().__init__()
        self.instance = instance

    def collect(self) -> Iterator[Metric]:
        for metric in super().collect():
            labelled = copy.copy(metric)  # the families are built per scrape, but the histograms' are kept
            labelled.samples = [s._replace(labels={**s.labels, INSTANCE_LABEL: self.instance}) for s in metric.samples]
            yield labelled


class ServiceMetrics:
    """One registry per service (several in one process in the tests): the histograms, the collector and the
    process's own metrics (CPU, memory, start time), every series labelled with the instance's name."""

    def __init__(self, instance: str) -> None:
        # No *_created series (process-wide in prometheus_client): Prometheus would store each as one more
        # series per histogram and source, for a start time nobody queries.
        disable_created_metrics()
        self.registry = InstanceLabel(instance)
        self.timings = FrameTimings(self.registry)  # the stats' events: built first, given to them at construction
        ProcessCollector(registry=self.registry)

    def collect(self, sources: MetricsSources) -> None:
        """Read the status at each scrape (once the service whose status it is exists)."""
        self.registry.register(StatusCollector(sources))
