"""The metrics without a bus: what the exposition says after given events, names by Prometheus's conventions,
a forgotten source's series gone, bounded labels, every metric documented (docs/metrics.md)."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import pytest
from fakes import Clock, pipeline
from gcdtrav.schemas.experience import CalibrationFigures
from gcdtrav.schemas.settings import SettingsError, load_settings
from gcdtrav.service.runtime.fleet.anchor_switch import AnchorSwitch
from gcdtrav.service.runtime.history import FrameHistory
from gcdtrav.service.runtime.intake.clock_offset import ClockOffsets
from gcdtrav.service.runtime.intake.presence import SourcePresence
from gcdtrav.service.runtime.intake.sources import SourceTracker
from gcdtrav.service.runtime.metrics import (
    CALIBRATION_EVERY_S,
    HELP,
    INSTANCE_LABEL,
    MetricsSources,
    ServiceMetrics,
    ThrottledCalibration,
)
from gcdtrav.service.runtime.progress import ProgressMonitor
from gcdtrav.service.runtime.schedule.latest_queue import LatestFrameQueue
from gcdtrav.service.runtime.stats import REFUSED_SOURCES, ServiceStats
from gcdtrav.service.runtime.status import StatusParts
from gcdtrav.service.store.outbox import store_status
from gcdtrav.service.store.sqlite import SqliteStore
from prometheus_client import generate_latest
from prometheus_client.parser import text_string_to_metric_families

from tools.loopback import admit, sqlite_outbox

DOCS = Path(__file__).resolve().parents[3] / "docs" / "metrics.md"


class Service:
    """The runtime parts a status reads, with the metrics over them as the node wires them."""

    def __init__(self, tmp_path: Path, max_sources: int = 3, owned: int = 0) -> None:
        self.clock = Clock()
        run = pipeline()
        self.queue: LatestFrameQueue[bytes] = LatestFrameQueue(10_000_000)
        self.sources = SourceTracker(max_sources=max_sources, idle_s=60.0)
        self.metrics = ServiceMetrics("box-1")
        self.stats = ServiceStats(logging.getLogger("test"), events=self.metrics.timings)
        self.offsets = ClockOffsets(5.0, 300.0)
        self.progress = ProgressMonitor(2.0, self.clock)
        switch = AnchorSwitch(run, SqliteStore(tmp_path / "store.sqlite3"), "box-1", 65536)
        history = FrameHistory(2)
        self.parts = StatusParts(
            "box-1", 0.0, run, switch, self.queue, history, self.stats, self.sources, self.progress, self.offsets
        )
        self.owned = owned
        self.store = sqlite_outbox(tmp_path / "store.sqlite3", 100, 10**6)  # the node's store, as it is wired
        status = lambda: self.parts.status(1.0, store=store_status(self.store.state()))  # noqa: E731
        self.presence = SourcePresence(max_sources, 60.0, lambda: self.clock.now)
        heard = self.presence.heard
        self.metrics.collect(MetricsSources(status, lambda: self.owned, 5.0, heard=heard))

    def frame(self, source: str, map_age_s: float = 0.3, reused: bool = False) -> None:
        """A frame received, taken and published."""
        admit(self.sources, source)
        self.queue.put(source, b"x", 1)
        self.queue.take(0)
        self.stats.waited(0.02)
        if reused:
            self.stats.unchanged(source, map_age_s)
        else:
            self.stats.processed(source, 1, 40.0, 25.0, map_age_s)

    def forget(self, source: str) -> None:
        self.queue.forget(source)
        self.stats.forget(source)

    def samples(self) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
        """Every sample by name and labels, less the instance's name that every one carries (checked)."""
        text = generate_latest(self.metrics.registry).decode()
        found = [sample for family in text_string_to_metric_families(text) for sample in family.samples]
        assert all(sample.labels.get(INSTANCE_LABEL) == "box-1" for sample in found), text
        return {
            (sample.name, tuple(sorted((k, v) for k, v in sample.labels.items() if k != INSTANCE_LABEL))): sample.value
            for sample in found
        }

    def value(self, name: str, **labels: str) -> float | None:
        return self.samples().get((name, tuple(sorted(labels.items()))))


def test_counts_and_histograms_follow_the_frames(tmp_path: Path) -> None:
    service = Service(tmp_path, owned=2)
    service.frame("r1/front", map_age_s=0.3)
    service.frame("r1/front", map_age_s=1.2, reused=True)
    service.frame("r2/front", map_age_s=4.5)
    service.stats.stale("r2/front")
    service.stats.rejected("r2/front", "undecodable", "not an image")
    service.stats.rejected_unread("rate_limited", lambda: "publisher x")
    service.offsets.observe("r1/front", 100.0, 100.25)
    assert service.value("gcdtrav_frames_received_total", source="r1/front") == 2
    assert service.value("gcdtrav_frames_processed_total", source="r1/front") == 1
    assert service.value("gcdtrav_frames_reused_total", source="r1/front") == 1
    assert service.value("gcdtrav_frames_dropped_total", source="r2/front", reason="stale") == 1
    assert service.value("gcdtrav_frames_rejected_total", source="r2/front", reason="undecodable") == 1
    assert service.value("gcdtrav_inputs_rejected_total", reason="rate_limited") == 1  # no source: instance-wide
    assert service.value("gcdtrav_inputs_rejected_total", reason="undecodable") == 1
    assert service.value("gcdtrav_clock_offset_seconds", source="r1/front") == pytest.approx(0.25)
    assert service.value("gcdtrav_clock_offset_seconds", source="r2/front") is None  # no stamped frame
    # Histograms, observed at the events: one inference per inferred frame, one age per published map.
    assert service.value("gcdtrav_inference_seconds_count") == 2
    assert service.value("gcdtrav_inference_seconds_sum") == pytest.approx(0.05)
    assert service.value("gcdtrav_queue_wait_seconds_count") == 3
    assert service.value("gcdtrav_map_age_seconds_count", source="r1/front") == 2
    assert service.value("gcdtrav_map_age_seconds_bucket", source="r1/front", le="1.0") == 1  # 0.3 s, not 1.2 s
    assert service.value("gcdtrav_map_age_seconds_bucket", source="r2/front", le="4.0") == 0
    assert service.value("gcdtrav_map_age_seconds_bucket", source="r2/front", le="5.0") == 1
    assert service.value("gcdtrav_sources_owned") == 2 and service.value("gcdtrav_sources_tracked") == 2
    assert service.value("gcdtrav_sources_max") == 3 and service.value("gcdtrav_instances_live") == 1
    assert service.value("gcdtrav_max_frame_age_seconds") == 5.0
    assert service.value("gcdtrav_healthy") == 1
    info = [labels for (name, labels) in service.samples() if name == "gcdtrav_service_info"]
    version = service.parts.anchors.head().version
    running = (("anchor_set_version", version), ("method", "gcd"), ("model", "fake"), ("name", "box-1"))
    assert info == [(*running, ("precision", "-"))]


def test_a_stalled_worker_reads_unhealthy(tmp_path: Path) -> None:
    service = Service(tmp_path)
    service.queue.put("r1/front", b"x", 1)
    service.clock.now = 5.0  # no beat for 5 s with a frame queued: stalled
    service.progress.check(len(service.queue))
    assert service.value("gcdtrav_healthy") == 0 and service.value("gcdtrav_queued_frames") == 1


def test_a_forgotten_source_leaves_no_series(tmp_path: Path) -> None:
    service = Service(tmp_path)
    service.frame("r1/front")
    service.frame("r2/front")
    service.offsets.observe("r1/front", 100.0, 100.1)
    assert any(("source", "r1/front") in labels for _, labels in service.samples())
    service.forget("r1/front")
    service.offsets.forget("r1/front")
    left = {name for name, labels in service.samples() if ("source", "r1/front") in labels}
    assert left == set()
    assert service.value("gcdtrav_map_age_seconds_count", source="r2/front") == 1  # the others stay
    service.frame("r1/front")  # back: counted from zero
    assert service.value("gcdtrav_frames_processed_total", source="r1/front") == 1


def test_series_stay_bounded_by_max_sources_and_the_refused_list(tmp_path: Path) -> None:
    service = Service(tmp_path, max_sources=256)
    for k in range(300):
        source = f"robot{k}/front"
        if admit(service.sources, source):
            service.frame(source)
            service.stats.stale(source)
        else:  # no slot: refused, listed (bounded) with why
            service.stats.rejected(source, "too_many_sources", "no slot left", tracked=False)
    per_source = {labels for _, labels in service.samples() if any(key == "source" for key, _ in labels)}
    sources = {dict(labels)["source"] for labels in per_source}
    assert len(sources) == 256 + REFUSED_SOURCES
    series_per_source = max(sum(dict(labels)["source"] == s for labels in per_source) for s in sources)
    assert len(per_source) <= len(sources) * series_per_source
    assert series_per_source <= 30  # counters by reason, offset, the age histogram's buckets
    assert service.value("gcdtrav_sources_tracked") == 256


def test_names_follow_prometheus_conventions_and_are_documented(tmp_path: Path) -> None:
    service = Service(tmp_path)
    service.frame("r1/front")
    service.stats.stale("r1/front")
    service.stats.rejected("r1/front", "undecodable", "x")
    text = generate_latest(service.metrics.registry).decode()
    families = {family.name: family for family in text_string_to_metric_families(text)}
    docs = DOCS.read_text("utf-8")
    ours = {name: family for name, family in families.items() if name.startswith("gcdtrav_")}
    assert set(families) - set(ours) <= {f"process_{n}" for n in ("cpu_seconds", "open_fds", "max_fds",
        "virtual_memory_bytes", "resident_memory_bytes", "start_time_seconds")}  # fmt: skip
    for name, family in ours.items():
        assert re.fullmatch(r"gcdtrav_[a-z0-9_]+", name), name
        assert f"`{name}" in docs, f"{name} is not documented in docs/metrics.md"
        if family.type == "counter":
            assert all(s.name.endswith("_total") for s in family.samples), name
        if family.type == "histogram":
            assert name.endswith("_seconds"), name
        for sample in family.samples:
            labels = set(sample.labels) - {INSTANCE_LABEL}
            assert labels <= {"source", "reason", "le", "alpha"} or name == "gcdtrav_service_info", sample
    assert not [line for line in text.splitlines() if "_created" in line]
    exposed = {f"{n}_info" if n == "gcdtrav_service" else n for n in HELP}
    assert exposed - {n for n in HELP if n.startswith(("gcdtrav_calibration", "gcdtrav_experience"))} <= set(ours)


def figures(pairs: int, ece: float | None) -> CalibrationFigures:
    return CalibrationFigures(
        pairs=pairs, mae=0.1 if pairs else None, bias=None, coverage={"0.1": 0.88 if pairs else None}, tau=0.3,
        reliability=[], ece=ece, ause=None, spearman_u_error=None, anchors=[],
    )  # fmt: skip


def test_every_series_names_the_instance_the_process_metrics_too(tmp_path: Path) -> None:
    service = Service(tmp_path)
    service.frame("r1/front")
    text = generate_latest(service.metrics.registry).decode()
    found = [sample for family in text_string_to_metric_families(text) for sample in family.samples]
    names = {sample.name for sample in found}
    assert {"gcdtrav_frames_processed_total", "gcdtrav_service_info", "gcdtrav_inference_seconds_bucket"} <= names
    assert {sample.labels.get(INSTANCE_LABEL) for sample in found} == {"box-1"}
    info = next(sample for sample in found if sample.name == "gcdtrav_service_info")
    assert info.labels["name"] == info.labels[INSTANCE_LABEL]


def test_sources_heard_say_when_their_last_frame_came_and_whether_they_parked(tmp_path: Path) -> None:
    service = Service(tmp_path)
    service.clock.now = 1000.0
    service.presence.frame("r1/front")
    service.clock.now = 1002.0
    service.presence.relay_health("r2/front", parked=True)  # its relay spoke, its camera never sent a frame
    service.clock.now = 1005.0
    service.presence.relay_health("r1/front", parked=False)
    assert service.value("gcdtrav_source_last_frame_timestamp_seconds", source="r1/front") == 1000.0
    assert service.value("gcdtrav_source_last_frame_timestamp_seconds", source="r2/front") == 1002.0
    assert service.value("gcdtrav_source_parked", source="r1/front") == 0
    assert service.value("gcdtrav_source_parked", source="r2/front") == 1
    service.presence.frame("r3/front")  # no relay: no parked series, it never said
    assert service.value("gcdtrav_source_parked", source="r3/front") is None
    service.clock.now = 1064.0  # 60 s (source_idle_s here) after r2 was last heard: forgotten, r1 still heard
    assert service.value("gcdtrav_source_parked", source="r2/front") is None
    assert service.value("gcdtrav_source_last_frame_timestamp_seconds", source="r1/front") == 1000.0


def test_sources_heard_stay_bounded_by_max_sources(tmp_path: Path) -> None:
    service = Service(tmp_path, max_sources=4)
    for k in range(10):
        service.presence.frame(f"robot{k}/front")
    service.presence.relay_health("x" * 300, parked=True)  # a name no intake accepts
    heard = {dict(labels)["source"] for name, labels in service.samples() if name.startswith("gcdtrav_source_")}
    assert heard == {f"robot{k}/front" for k in range(6, 10)}  # the ones heard longest ago evicted


def test_calibration_is_recomputed_until_pairs_come_then_at_most_every_interval(tmp_path: Path) -> None:
    clock, computed = Clock(), []
    answers = iter([figures(0, None), figures(40, 0.05), figures(80, 0.04)])

    def compute() -> CalibrationFigures:
        computed.append(clock.now)
        return next(answers)

    throttled = ThrottledCalibration(compute, clock)
    assert throttled.figures().pairs == 0  # type: ignore[union-attr]
    clock.now += 1
    assert throttled.figures().ece == 0.05  # type: ignore[union-attr]  # no pairs before: asked again at once
    clock.now += CALIBRATION_EVERY_S - 1
    assert throttled.figures().ece == 0.05 and len(computed) == 2  # type: ignore[union-attr]
    clock.now += 1
    assert throttled.figures().ece == 0.04 and len(computed) == 3  # type: ignore[union-attr]


def test_calibration_metrics_where_experience_is_on(tmp_path: Path) -> None:
    service = Service(tmp_path)
    service.metrics = ServiceMetrics("box-1")
    service.metrics.collect(
        MetricsSources(lambda: service.parts.status(1.0), lambda: 0, None, lambda: figures(40, 0.05))
    )
    assert service.value("gcdtrav_calibration_ece") == 0.05 and service.value("gcdtrav_calibration_pairs") == 40
    assert service.value("gcdtrav_calibration_coverage", alpha="0.1") == 0.88
    assert service.value("gcdtrav_max_frame_age_seconds") is None  # max_frame_age_s: null
    off = Service(tmp_path)
    assert not [name for name, _ in off.samples() if "calibration" in name]


@pytest.mark.parametrize(
    ("environ", "port"), [({}, 0), ({"GCDTRAV_METRICS_PORT": "9447"}, 9447), ({"GCDTRAV_METRICS_PORT": "65535"}, 65535)]
)
def test_the_metrics_port_setting_and_its_environment_variable(environ: dict[str, str], port: int) -> None:
    settings = load_settings(environ=environ)
    assert settings.metrics_port == port and settings.metrics_address == "0.0.0.0"


@pytest.mark.parametrize("value", ["-1", "65536", "http"])
def test_a_metrics_port_outside_tcp_ports_is_refused(value: str) -> None:
    with pytest.raises(SettingsError, match="metrics_port"):
        load_settings(environ={"GCDTRAV_METRICS_PORT": value})
