"""A real Prometheus (Debian's /usr/bin/prometheus) scrapes `gcdtrav serve` instances on loopback: its PromQL
answers agree with what the robots received, every query of the Grafana dashboard returns data and no NaN (an
idle instance scraped too), every series names its gcdtrav instance, an instance joins and leaves mid-stream,
and the silent-robot alert fires for a robot that went silent, not for one that parked and said so. One
Prometheus, one router and the instances are shared by the module's tests.
"""

from __future__ import annotations

import json
import math
import signal
import subprocess
import tempfile
import threading
import time
import urllib.parse
import urllib.request
from collections import Counter
from collections.abc import Iterator
from contextlib import closing, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import pytest
import yaml
from conftest import textured_image
from real_components import require_prometheus
from zenoh_helpers import (
    client_config,
    connecting_config,
    free_port,
    serve_args,
    start_router,
    subscribed_elsewhere,
    wait_until,
)

pytest.importorskip("torch")

from gcdtrav.client import Maps, QueryTimeout, TraversabilityClient
from gcdtrav.schemas.keys import Keys, input_key
from gcdtrav.schemas.messages import RelayHealth
from gcdtrav.schemas.settings import ServiceSettings

from tools.loopback import SimulatedRobots, in_process_service, wait_for_statuses

ROOT = Path(__file__).resolve().parents[3]
DASHBOARD = ROOT / "deploy" / "grafana" / "gcdtrav.json"
ALERTS = ROOT / "deploy" / "prometheus" / "alerts.yaml"
SILENT_AFTER_S = 3  # the test's silent-robot rule: the shipped one waits 60 s, then 1 min
ROBOTS = [f"r{k}/front" for k in range(4)]
FPS = 2.0
IMAGE = textured_image(48, 64)
JPEG = cv2.imencode(".jpg", IMAGE)[1].tobytes()  # one view: after the first, maps are reused (and refreshed)


class Robots(SimulatedRobots):
    """The robots streaming at FPS (tools/loopback.py); the maps they receive, whole (inferred or reused)."""

    def __init__(self, client: TraversabilityClient) -> None:
        super().__init__(client, ROBOTS, FPS, JPEG)
        self.maps: list[Maps] = []
        self.lock = threading.Lock()

    def on_maps(self, maps: Maps) -> None:
        with self.lock:
            self.maps.append(maps)

    def received(self, source: str, reused: bool) -> int:
        with self.lock:
            return sum(m.header.source == source and m.reused == reused for m in self.maps)

    def instances_serving(self, source: str) -> set[str]:
        with self.lock:
            return {m.header.instance for m in self.maps if m.header.source == source}

    def published(self) -> dict[str, tuple[int, int]] | None:
        """Per robot, the maps the live instances say they published, (inferred, reused), from their statuses
        (None if one does not answer). The maps received can be fewer: maps are published with congestion
        control DROP, and a loaded host's router drops some on the way."""
        try:
            statuses = self.client.statuses(timeout=2.0)
        except QueryTimeout:
            return None
        totals = {robot: (0, 0) for robot in ROBOTS}
        for status in statuses:
            for robot in ROBOTS:
                counts = status.sources.get(robot)
                if counts is not None:
                    inferred, reused = totals[robot]
                    totals[robot] = (inferred + counts.processed, reused + counts.unchanged)
        return totals


@dataclass
class Fleet:
    model: Path
    state: Path
    router_port: int
    ports: dict[str, int]  # instance -> metrics port (box-c joins later)
    prometheus_url: str
    processes: dict[str, subprocess.Popen[str]] = field(default_factory=dict)

    def start(self, name: str, prefix: str = "gcdtrav") -> subprocess.Popen[str]:
        args = serve_args(
            self.model,
            *("-m", "client", "-e", f"tcp/127.0.0.1:{self.router_port}", "--instance", name),
            *("--prefix", prefix, "--input", f"{prefix}/in/**"),
            *("--state-dir", str(self.state / name), "--no-preview", "--threads", "1"),
            *("--metrics-port", str(self.ports[name]), "--metrics-address", "127.0.0.1"),
        )
        process = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, text=True)
        self.processes[name] = process
        return process

    def query(self, expr: str) -> list[dict[str, Any]]:
        """An instant query's result vector (HTTP API /api/v1/query)."""
        url = f"{self.prometheus_url}/api/v1/query?" + urllib.parse.urlencode({"query": expr})
        with urllib.request.urlopen(url, timeout=10) as response:
            body = json.load(response)
        assert body["status"] == "success", body
        return list(body["data"]["result"])

    def by(self, expr: str, label: str) -> dict[str, float]:
        return {sample["metric"].get(label, ""): float(sample["value"][1]) for sample in self.query(expr)}

    def scalar(self, expr: str) -> float | None:
        result = self.query(expr)
        return float(result[0]["value"][1]) if result else None


def short_silent_rule(storage: Path) -> Path:
    """The shipped GcdtravRobotSilent with SILENT_AFTER_S and no ``for``, so that the test runs in seconds;
    everything else of the rule (the memory, the parked exception) as shipped."""
    rules = yaml.safe_load(ALERTS.read_text("utf-8"))
    rule = next(r for group in rules["groups"] for r in group["rules"] if r.get("alert") == "GcdtravRobotSilent")
    assert rule["expr"].count("> 60") == 1, rule["expr"]  # the shipped threshold, replaced below
    short = {**rule, "expr": rule["expr"].replace("> 60", f"> {SILENT_AFTER_S}"), "for": "0s"}
    path = storage / "silent_short.yaml"
    path.write_text(json.dumps({"groups": [{"name": "gcdtrav-test-short", "rules": [short]}]}))
    return path


def prometheus_config(ports: dict[str, int], storage: Path) -> Path:
    """Scrape every second: the fleet's instances (job gcdtrav), the experience instance apart (a fleet of its
    own, so that the fleet's sums stay the robots'), an idle instance (a prefix no robot uses) apart too."""

    def job(name: str, instances: list[str]) -> dict[str, Any]:
        return {"job_name": name, "static_configs": [{"targets": [f"127.0.0.1:{ports[i]}" for i in instances]}]}

    config = storage / "prometheus.yml"
    config.write_text(
        json.dumps(  # JSON is YAML
            {
                "global": {"scrape_interval": "1s", "evaluation_interval": "1s", "scrape_timeout": "900ms"},
                "rule_files": [str(ALERTS), str(short_silent_rule(storage))],
                "scrape_configs": [
                    job("gcdtrav", ["box-a", "box-b", "box-c"]),
                    job("gcdtrav-experience", ["exp-1"]),
                    job("gcdtrav-idle", ["idle-1"]),
                ],
            }
        )
    )
    return config


@pytest.fixture(scope="module")
def fleet(tiny_model_dir: Path) -> Iterator[Fleet]:
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        router_port, web_port = free_port(), free_port()
        router = start_router(router_port)
        ports = {name: free_port() for name in ("box-a", "box-b", "box-c", "exp-1", "idle-1")}
        storage = tmp_path / "prometheus"
        storage.mkdir()
        prometheus_bin = require_prometheus()  # skipped here without it; a failure in CI (GCDTRAV_REQUIRE)
        log = (storage / "prometheus.log").open("w")  # a file: an unread pipe would fill and block it
        prometheus = subprocess.Popen(
            [
                prometheus_bin,
                f"--config.file={prometheus_config(ports, storage)}",
                f"--storage.tsdb.path={storage / 'data'}",
                f"--web.listen-address=127.0.0.1:{web_port}",
                "--log.level=warn",
            ],
            stdout=subprocess.DEVNULL,
            stderr=log,
            text=True,
        )
        fleet = Fleet(tiny_model_dir, tmp_path, router_port, ports, f"http://127.0.0.1:{web_port}")
        try:
            fleet.start("box-a")
            fleet.start("box-b")
            assert wait_until(lambda: ready(fleet.prometheus_url), 60), "prometheus did not become ready"
            yield fleet
        finally:
            for process in [*fleet.processes.values(), prometheus, router]:
                if process.poll() is None:
                    process.terminate()
            for process in [*fleet.processes.values(), prometheus, router]:
                try:
                    process.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    process.kill()
            log.close()


def ready(url: str) -> bool:
    try:
        with urllib.request.urlopen(f"{url}/-/ready", timeout=2) as response:
            return response.status == 200
    except OSError:
        return False


@pytest.fixture(scope="module")
def robots(fleet: Fleet) -> Iterator[Robots]:
    """The robots streamed for a few seconds to two instances, one stale frame and one undecodable input
    among them; stopped, and every instance's counts scraped."""
    client = TraversabilityClient(config=client_config(fleet.router_port), timeout=5.0)
    fleet_robots = Robots(client)
    subscriber = client.subscribe_maps("**", fleet_robots.on_maps)
    try:
        wait_for_statuses(client, 2, timeout_s=120)
        assert wait_until(lambda: fleet.scalar("sum(gcdtrav_instances_live)") == 4, 60), "both see both"
        fleet_robots.start()
        assert wait_until(lambda: all(fleet_robots.received(r, False) for r in ROBOTS), 60), "maps for every robot"
        client.publish_image(ROBOTS[0], IMAGE, stamp=time.time() - 60)  # dropped stale at intake
        client.session.put("gcdtrav/in/junk/cam", b"\x00 not an image")  # rejected
        assert wait_until(lambda: stale_and_junk_counted(fleet), 60), "the stale frame and the junk input scraped"
        yield fleet_robots
    finally:
        fleet_robots.stop()
        subscriber.undeclare()
        client.close()


def stale_and_junk_counted(fleet: Fleet) -> bool:
    stale = fleet.scalar('sum(gcdtrav_frames_dropped_total{source="r0/front", reason="stale"})')
    return stale is not None and stale >= 1 and (fleet.scalar("sum(gcdtrav_inputs_rejected_total)") or 0) >= 1


def settled(fleet: Fleet, robots: Robots, processed: str, reused: str) -> tuple[bool, str]:
    """Whether Prometheus's per-source counts equal the maps the instances published (and what differs): the
    maps counted, and one map age per map and one inference per inferred map (counted at other moments than
    the maps, so possibly in a later scrape)."""
    got_processed, got_reused = fleet.by(processed, "source"), fleet.by(reused, "source")
    expected = robots.published()
    if expected is None:
        return False, "an instance did not answer its status"
    found = {r: (got_processed.get(r), got_reused.get(r)) for r in ROBOTS}
    ages = fleet.by("sum by (source) (gcdtrav_map_age_seconds_count)", "source")
    expected_ages = {r: float(sum(expected[r])) for r in ROBOTS}
    inferences = fleet.scalar("sum(gcdtrav_inference_seconds_count)")
    expected_inferences = sum(inferred for inferred, _ in expected.values())
    agree = found == expected and ages == expected_ages and inferences == expected_inferences
    return agree, (
        f"prometheus {found}, robots {expected}; map ages {ages} (expected {expected_ages}); "
        f"inferences {inferences} (expected {expected_inferences})"
    )


def test_prometheus_counts_agree_with_the_maps_the_robots_received(fleet: Fleet, robots: Robots) -> None:
    robots.stop()
    processed = "sum by (source) (gcdtrav_frames_processed_total)"
    reused = "sum by (source) (gcdtrav_frames_reused_total)"
    assert wait_until(lambda: settled(fleet, robots, processed, reused)[0], 60), settled(
        fleet, robots, processed, reused
    )[1]
    published = robots.published()
    assert published is not None
    for robot in ROBOTS:  # every map received was counted; some may have been dropped on the way
        assert 0 < robots.received(robot, False) <= published[robot][0], (robot, published)
        assert robots.received(robot, True) <= published[robot][1], (robot, published)
    assert fleet.scalar("sum(gcdtrav_sources_owned)") == len(ROBOTS)  # the fleet's table, split between them
    owned = fleet.by("gcdtrav_sources_owned", "instance")
    assert sorted(owned.values()) == [2.0, 2.0], owned  # bounded loads: 4 robots on 2 instances
    assert fleet.by("gcdtrav_healthy", "instance") == {f"127.0.0.1:{fleet.ports[b]}": 1.0 for b in ("box-a", "box-b")}
    assert fleet.by("gcdtrav_service_info", "name").keys() == {"box-a", "box-b"}
    assert fleet.by("up", "instance")[f"127.0.0.1:{fleet.ports['box-c']}"] == 0.0  # not started yet
    # The histograms (one map age per published map, one inference per inferred one: in settled above).
    assert fleet.scalar("sum(gcdtrav_queue_wait_seconds_count)") >= sum(robots.received(r, False) for r in ROBOTS)
    p95 = fleet.scalar("histogram_quantile(0.95, sum by (le) (gcdtrav_map_age_seconds_bucket))")
    assert p95 is not None and 0 < p95 <= 5.0  # never over max_frame_age_s: older frames are dropped
    # The stale frame and the junk input, by reason.
    assert fleet.scalar('sum(gcdtrav_frames_dropped_total{source="r0/front", reason="stale"})') == 1
    assert fleet.scalar("sum(gcdtrav_inputs_rejected_total)") == 1
    offsets = fleet.by("max by (source) (gcdtrav_clock_offset_seconds)", "source")
    assert set(offsets) == set(ROBOTS) and all(abs(v) < 1 for v in offsets.values()), offsets  # one clock here


def test_an_instance_joins_and_leaves_mid_stream(fleet: Fleet, robots: Robots) -> None:
    robots.start()
    try:
        box_c = fleet.start("box-c")
        target_c = f"127.0.0.1:{fleet.ports['box-c']}"
        assert wait_until(lambda: fleet.by("gcdtrav_instances_live", "instance").get(target_c) == 3, 90), "joined"
        assert wait_until(lambda: fleet.by("gcdtrav_sources_owned", "instance").get(target_c, 0) >= 1, 60)
        assert wait_until(lambda: fleet.scalar("sum(gcdtrav_sources_owned)") == len(ROBOTS), 60)
        assert wait_until(lambda: any("box-c" in robots.instances_serving(r) for r in ROBOTS), 60), "c serves"
        moved = [r for r in ROBOTS if "box-c" in robots.instances_serving(r)]
        box_c.send_signal(signal.SIGTERM)
        box_c.wait(30)
        assert wait_until(lambda: fleet.by("up", "instance").get(target_c) == 0.0, 60)
        assert wait_until(lambda: fleet.scalar("sum(gcdtrav_sources_owned)") == len(ROBOTS), 60)  # c's series stale
        # the others see c's token go at once, but their next scrape may come a second later
        assert wait_until(lambda: set(fleet.by("gcdtrav_instances_live", "instance").values()) == {2.0}, 60)
        # box-c's robots go back to the others: each is then served by c and by another instance
        assert wait_until(lambda: all(len(robots.instances_serving(r)) >= 2 for r in moved), 60), {
            r: robots.instances_serving(r) for r in moved
        }
    finally:
        robots.stop()
    # Every count the instances made, box-c's last scrape included, against what the live instances say they
    # published: exact for the robots box-c never served; for those it did, box-c's scraped share on top (its
    # last frames may have gone out after its last scrape). The maps received: at most the counts (DROP).
    processed = "sum by (source) (max_over_time(gcdtrav_frames_processed_total[10m]))"
    reused = "sum by (source) (max_over_time(gcdtrav_frames_reused_total[10m]))"

    def counts_agree() -> bool:  # once the remaining instances' last counts are scraped
        counted, counted_reused = fleet.by(processed, "source"), fleet.by(reused, "source")
        published = robots.published()  # by the instances still live: box-c's share is gone from it
        if published is None:
            return False
        of_c = f'{{instance="{target_c}"}}[10m]'  # what box-c counted as published, as last scraped
        served_by_c = fleet.by(
            f"max_over_time(gcdtrav_frames_processed_total{of_c}) + max_over_time(gcdtrav_frames_reused_total{of_c})",
            "source",
        )
        for robot in ROBOTS:
            found = counted.get(robot), counted_reused.get(robot)
            received = robots.received(robot, False), robots.received(robot, True)
            if found[0] is None or found[1] is None:
                return False
            # box-c's share: as last scraped, or seen by the robot only (served after box-c's last scrape)
            if served_by_c.get(robot) or "box-c" in robots.instances_serving(robot):
                if not (found[0] >= published[robot][0] and found[1] >= published[robot][1]):
                    return False
            elif found != published[robot] or not (received[0] <= found[0] and received[1] <= found[1]):
                return False
        return True

    assert wait_until(counts_agree, 60), (
        fleet.by(processed, "source"),
        fleet.by(reused, "source"),
        robots.published(),
        {r: (robots.received(r, False), robots.received(r, True)) for r in ROBOTS},
    )
    assert Counter(fleet.by("gcdtrav_healthy", "instance").values()) == Counter({1.0: 2})


def dashboard_queries() -> list[tuple[str, str]]:
    dashboard = json.loads(DASHBOARD.read_text("utf-8"))
    return [(panel["title"], target["expr"]) for panel in dashboard["panels"] for target in panel["targets"]]


@contextmanager
def experience_instance(port: int, state: Path) -> Iterator[None]:
    """An instance with experience on (its own session: a fleet of one), driven by the synthetic robot until
    it has pairs to grade, its metrics on ``port``."""
    from gcdtrav.service.runtime.http_endpoints import Checks, HttpEndpoints

    from tools.robot_drive import BusRobot, experience_settings, grid_settings
    from tools.synthetic_scene import SceneBackend, make_world, start_anchors

    settings = ServiceSettings(
        state_dir=state,
        instance="exp-1",
        preview=False,
        max_frame_age_s=None,  # simulated time from a stamp in the past, like a replayed bag
        max_stamp_skew_s=None,
        grids=[grid_settings()],
        experience=experience_settings(),
        metrics_port=port,
        metrics_address="127.0.0.1",
    )
    with (
        in_process_service(SceneBackend(), settings, start_anchors()) as (service, zenoh_port),
        closing(HttpEndpoints(settings)) as http,
        TraversabilityClient(config=connecting_config(zenoh_port), timeout=5.0) as client,
    ):
        http.serve(Checks(service.liveness, service.readiness, service.metrics.registry))
        robot = BusRobot(client, make_world(seed=0))
        robot.drive(25.0, seed=1)
        robot.close()
        yield


def relay_health(source: str, parked: bool) -> RelayHealth:
    """What a robot's relay sends over the link (client/relay/relay.py), with only what the service reads set."""
    return RelayHealth(
        source=source,
        published_at=time.time(),
        newest_map_stamp=None,
        map_age_s=None,
        stale=True,
        stale_after_s=3.0,
        frames_captured=0,
        frames_sent=0,
        credit_timeouts=0,
        uplink_bytes_per_s=0.0,
        downlink_bytes_per_s=0.0,
        parked=parked,
    )


def test_every_query_of_the_dashboard_returns_data_and_no_nan_with_an_idle_instance(
    fleet: Fleet, robots: Robots
) -> None:
    """Each expression of deploy/grafana/gcdtrav.json, with Grafana's rate window filled in, answers a finite
    value while the robots stream and the experience instance has graded its pairs; and none answers NaN while
    an instance that owns no robot (no inference, no queue wait: quantiles of nothing) is scraped too."""
    queries = dashboard_queries()
    assert len(queries) >= 15 and any("calibration" in expr for _, expr in queries)
    fleet.start("idle-1", prefix="idle")
    idle = 'gcdtrav_sources_owned{gcdtrav_instance="idle-1"}'
    # scraped for a while: its histograms' rates are 0 over the window
    assert wait_until(lambda: (fleet.scalar(f"count_over_time({idle}[1m])") or 0) >= 5, 120), "idle-1 scraped"
    robots.start()
    try:
        with (
            experience_instance(fleet.ports["exp-1"], fleet.state / "exp-1"),
            TraversabilityClient(config=client_config(fleet.router_port), timeout=5.0) as client,
        ):
            # the services' relay-health subscriptions known to this new session: its one put is not lost
            assert subscribed_elsewhere(client.session, Keys().relay_health(ROBOTS[0])), "relay health unheard"
            client.session.put(Keys().relay_health(ROBOTS[0]), relay_health(ROBOTS[0], parked=False).pack())
            target = f"127.0.0.1:{fleet.ports['exp-1']}"
            assert wait_until(lambda: fleet.by("gcdtrav_calibration_ece", "instance").get(target) is not None, 60)

            def answers() -> list[tuple[str, str, list[Any]]]:
                window = "2m"  # Grafana's $__rate_interval: at least four scrapes
                return [(title, e, fleet.query(e.replace("$__rate_interval", window))) for title, e in queries]

            def empty() -> list[tuple[str, str, list[Any]]]:
                return [(t, e, a) for t, e, a in answers() if not any(finite(sample) for sample in a)]

            assert wait_until(lambda: not empty(), 60), empty()
            nan = [(t, e, s) for t, e, a in answers() for s in a if math.isnan(float(s["value"][1]))]
            assert not nan, nan
            assert fleet.scalar(f"max_over_time({idle}[1m])") == 0  # it was idle all along
    finally:
        robots.stop()


def test_every_series_names_its_gcdtrav_instance(fleet: Fleet, robots: Robots) -> None:
    """The gcdtrav name on every series a gcdtrav instance exposes (Prometheus's own up, scrape_* and ALERTS excepted):
    a panel says which instance without joining the info metric."""
    unnamed = fleet.query(
        'count by (__name__) ({job=~"gcdtrav.*", gcdtrav_instance="", __name__!~"up|scrape_.*|ALERTS.*"})'
    )
    assert not unnamed, unnamed
    names = fleet.by('count by (gcdtrav_instance) ({job="gcdtrav", __name__=~"gcdtrav_.*"})', "gcdtrav_instance")
    assert {"box-a", "box-b"} <= set(names), names
    info = fleet.query("gcdtrav_service_info")
    assert info and all(s["metric"]["name"] == s["metric"]["gcdtrav_instance"] for s in info), info


def firing_silent(fleet: Fleet) -> set[str]:
    firing = fleet.query('ALERTS{alertname="GcdtravRobotSilent", alertstate="firing"}')
    return {sample["metric"]["source"] for sample in firing}


def test_a_silent_robot_fires_and_one_that_parked_and_said_so_does_not(fleet: Fleet) -> None:
    """Three robots stream; then one goes silent, one parks (its relay says so over the link) and stops, one
    streams on. The shipped rule, with SILENT_AFTER_S for 60 s and no wait, fires for the silent one only."""
    silent, parked, steady = "silent/front", "parked/front", "steady/front"
    keys = Keys()
    with TraversabilityClient(config=client_config(fleet.router_port), timeout=5.0) as client:
        # the services' subscriptions known to this new session: its puts and first frames are not lost
        assert subscribed_elsewhere(client.session, keys.relay_health(parked)), "relay health unheard"
        assert subscribed_elsewhere(client.session, input_key(client.input_prefix, silent)), "the inputs"
        client.session.put(keys.relay_health(parked), relay_health(parked, parked=False).pack())

        def stream(sources: list[str], seconds: float) -> None:
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                for source in sources:
                    client.publish_image(source, IMAGE)
                time.sleep(0.5)

        stream([silent, parked, steady], 3.0)
        heard = "max by (source) (gcdtrav_source_last_frame_timestamp_seconds)"
        assert wait_until(lambda: {silent, parked, steady} <= set(fleet.by(heard, "source")), 60), "all heard"
        client.session.put(keys.relay_health(parked), relay_health(parked, parked=True).pack())  # then stops
        assert wait_until(lambda: fleet.by("max by (source) (gcdtrav_source_parked)", "source").get(parked) == 1, 60)
        deadline = time.monotonic() + 60  # the bound of a failure only
        while silent not in firing_silent(fleet) and time.monotonic() < deadline:
            stream([steady], 1.0)
        firing = firing_silent(fleet)
        assert silent in firing, f"not firing for the silent robot after 60 s: {firing}"
        assert parked not in firing and steady not in firing, firing
        silence = fleet.by(f"time() - {heard}", "source")
        assert silence[parked] > SILENT_AFTER_S, silence  # silent as long: only its parking keeps it quiet
        client.session.put(keys.relay_health(parked), relay_health(parked, parked=False).pack())  # runs again, silent
        assert wait_until(lambda: parked in firing_silent(fleet), 60), "fires once it no longer says parked"


def finite(sample: dict[str, Any]) -> bool:
    return math.isfinite(float(sample["value"][1]))
