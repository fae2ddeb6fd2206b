"""The readiness rule behind /readyz, and both probes over HTTP on loopback."""

from __future__ import annotations

import urllib.error
import urllib.request

import pytest
from gcdtrav.service.runtime.probes import Health, Probes, ready

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
    try:
        with urllib.request.urlopen(url, timeout=5) as reply:
            return reply.status, reply.read().decode()
    except urllib.error.HTTPError as err:
        return err.code, err.read().decode()


def test_probes_answer_200_or_503_with_the_reason_in_one_line() -> None:
    state = {"ready": Health(False, "starting: not in the fleet yet")}
    probes = Probes(lambda: LIVE, lambda: state["ready"], "127.0.0.1", 0)
    probes.start()
    try:
        base = f"http://127.0.0.1:{probes.port}"
        assert get(f"{base}/livez") == (200, "ok\n")
        assert get(f"{base}/readyz") == (503, "starting: not in the fleet yet\n")
        state["ready"] = LIVE
        assert get(f"{base}/readyz") == (200, "ok\n")
        assert get(f"{base}/other")[0] == 404
    finally:
        probes.close()
