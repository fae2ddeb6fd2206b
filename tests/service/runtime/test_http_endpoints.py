"""The readiness rule behind /readyz, and the one HTTP home (probes and metrics) on loopback."""

from __future__ import annotations

import urllib.error
import urllib.request

import pytest
from gcdtrav.schemas.settings import ServiceSettings, SettingsError
from gcdtrav.service.runtime.http_endpoints import Checks, HttpEndpoints, listeners, ready
from gcdtrav.service.runtime.progress import Health
from prometheus_client import CollectorRegistry, Counter
from zenoh_helpers import free_port

LIVE, STALLED = Health(True), Health(False, "stalled: no inference finished for 30 s")


@pytest.mark.parametrize(
    ("health", "draining", "in_fleet", "expected"),
    [
        (LIVE, False, True, LIVE),
        (LIVE, True, True, Health(False, "draining: left the fleet, finishing the frame in flight")),
        (STALLED, True, True, Health(False, "draining: left the fleet, finishing the frame in flight")),
        (STALLED, False, True, STALLED),
        (STALLED, False, False, STALLED),  # the worker's problem first: it is what a restart would fix
        (LIVE, False, False, Health(False, "starting: not in the fleet yet")),
    ],
)
def test_ready_only_when_progressing_in_the_fleet_and_not_draining(
    health: Health, draining: bool, in_fleet: bool, expected: Health
) -> None:
    assert ready(health, draining, in_fleet) == expected


def get(url: str) -> tuple[int, str]:
    """Status and body; 0 when nothing listens."""
    try:
        with urllib.request.urlopen(url, timeout=30) as reply:  # bounds a failure
            return reply.status, reply.read().decode()
    except urllib.error.HTTPError as err:
        return err.code, err.read().decode()
    except urllib.error.URLError:
        return 0, ""


def http(health_port: int, metrics_port: int) -> HttpEndpoints:
    return HttpEndpoints(
        ServiceSettings(
            health_port=health_port, health_address="127.0.0.1", metrics_port=metrics_port, metrics_address="127.0.0.1"
        )
    )


def registry_counting() -> CollectorRegistry:
    registry = CollectorRegistry()
    Counter("gcdtrav_test_total", "a test counter", registry=registry).inc()
    return registry


def test_probes_answer_503_starting_until_the_service_is_handed_over_then_200_or_503_with_the_reason() -> None:
    state = {"ready": Health(False, "starting: not in the fleet yet")}
    port = free_port()
    endpoints = http(port, port)  # one port: probes and metrics, as the Kubernetes manifests have it
    try:
        base = f"http://127.0.0.1:{port}"
        assert get(f"{base}/livez") == (503, "starting: loading the model\n")
        endpoints.starting("warming up")
        assert get(f"{base}/readyz") == (503, "starting: warming up\n")
        assert get(f"{base}/metrics")[0] == 503
        endpoints.serve(Checks(lambda: LIVE, lambda: state["ready"], registry_counting()))
        assert get(f"{base}/livez") == (200, "ok\n")
        assert get(f"{base}/readyz") == (503, "starting: not in the fleet yet\n")
        state["ready"] = LIVE
        assert get(f"{base}/readyz") == (200, "ok\n")
        assert "gcdtrav_test_total 1.0" in get(f"{base}/metrics")[1]
        assert get(f"{base}/other")[0] == 404
    finally:
        endpoints.close()
    assert get(f"http://127.0.0.1:{port}/livez")[0] == 0  # closed


def test_two_ports_two_listeners_and_the_probes_port_does_not_name_the_sources() -> None:
    health_port, metrics_port = free_port(), free_port()
    endpoints = http(health_port, metrics_port)
    endpoints.serve(Checks(lambda: LIVE, lambda: LIVE, registry_counting()))
    try:
        assert sorted(endpoints.ports) == sorted([health_port, metrics_port])
        assert get(f"http://127.0.0.1:{health_port}/metrics")[0] == 404
        assert get(f"http://127.0.0.1:{metrics_port}/livez")[0] == 404
        assert get(f"http://127.0.0.1:{metrics_port}/metrics")[0] == 200
    finally:
        endpoints.close()


@pytest.mark.parametrize(
    ("health_port", "metrics_port", "count"), [(0, 0, 0), (8081, 0, 1), (0, 9447, 1), (8081, 9447, 2), (9447, 9447, 1)]
)
def test_the_pair_of_port_settings_at_its_edges(health_port: int, metrics_port: int, count: int) -> None:
    assert len(listeners(ServiceSettings(health_port=health_port, metrics_port=metrics_port))) == count


def test_one_port_with_two_addresses_is_refused_in_one_line() -> None:
    settings = ServiceSettings(health_port=9447, metrics_port=9447, metrics_address="127.0.0.1")
    with pytest.raises(SettingsError, match="addresses differ"):
        listeners(settings)


def test_a_taken_port_is_refused_naming_the_setting() -> None:
    port = free_port()
    first = http(port, 0)
    try:
        with pytest.raises(
            SettingsError, match=f"cannot serve the health probes on 127.0.0.1:{port} \\(health_port\\)"
        ):
            http(port, 0)
    finally:
        first.close()
