"""The service's one HTTP home: ``/livez`` and ``/readyz`` for a supervisor (Kubernetes' kubelet) and
``/metrics`` for Prometheus. No middleware here.

`gcdtrav serve` opens it first, before it loads the model: from the first second the probes answer 503
``starting: <what>`` (loading the model, measuring the modes, warming up), so a kubelet sees a pod starting,
not a closed port. Once the service runs, ``serve`` hands it the service's checks and metrics registry.
``health_port`` and ``metrics_port`` are a pair of settings: equal, one listener serves all three paths
(as the Kubernetes manifests do); different, one listener each, the probes' port without ``/metrics`` (it
names the fleet's sources, the probes only say ok or why not); 0 turns either off.

Each probe is answered from memory (no zenoh round trip, no model call), so a probe every few seconds costs
nothing and cannot fail because a router is away: 200 with ``ok``, or 503 with the reason, one line.
*Live*: the worker progresses (``progress.py``; a stalled one is restarted once the kubelet gives up).
*Ready*: the instance is in the fleet and serving (not starting, not stalled, not draining): a rolling
upgrade waits for it before it stops the next old pod.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

from gcdtrav.schemas.settings import ServiceSettings, SettingsError
from gcdtrav.service.runtime.progress import Health
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest

log = logging.getLogger("gcdtrav.service")
PROBES, METRICS = ("/livez", "/readyz"), "/metrics"


def ready(health: Health, draining: bool, in_fleet: bool) -> Health:
    """The readiness rule: not draining, the worker progressing, and a member of the fleet."""
    if draining:
        return Health(False, "draining: left the fleet, finishing the frame in flight")
    if not health.healthy:
        return health
    if not in_fleet:
        return Health(False, "starting: not in the fleet yet")
    return health


@dataclass(frozen=True)
class Checks:
    """What the endpoints read once the service runs."""

    live: Callable[[], Health]
    ready: Callable[[], Health]
    registry: CollectorRegistry


@dataclass(frozen=True)
class Listener:
    """One address and port and the paths it serves."""

    address: str
    port: int
    paths: tuple[str, ...]
    settings: str  # the setting(s) naming it, for the error of a taken port


def listeners(settings: ServiceSettings) -> list[Listener]:
    """health_port and metrics_port: one listener when they are equal, one each otherwise, none when 0."""
    health = Listener(settings.health_address, settings.health_port, PROBES, "health_port")
    metrics = Listener(settings.metrics_address, settings.metrics_port, (METRICS,), "metrics_port")
    if health.port and health.port == metrics.port:
        if health.address != metrics.address:
            raise SettingsError(
                f"health_port and metrics_port are both {health.port} but their addresses differ "
                f"({health.address}, {metrics.address}): one listener has one address"
            )
        return [Listener(health.address, health.port, (*PROBES, METRICS), "health_port and metrics_port")]
    return [listener for listener in (health, metrics) if listener.port]


class HttpEndpoints:
    """The probes and the metrics on the ports the settings name; serving from construction to close()."""

    def __init__(self, settings: ServiceSettings) -> None:
        self._lock = threading.Lock()
        self._checks: Checks | None = None
        self._starting = "starting: loading the model"
        self._servers: list[ThreadingHTTPServer] = []
        self._threads: list[threading.Thread] = []
        try:
            for listener in listeners(settings):
                self._listen(listener)
        except SettingsError:
            self.close()
            raise

    def _listen(self, listener: Listener) -> None:
        answer = self._answer
        paths = listener.paths

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                path = self.path.split("?", 1)[0]
                status, content_type, body = answer(path) if path in paths else not_found(paths)
                self.send_response(status)
                self.send_header("Content-Type", content_type)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, format: str, *args: object) -> None:
                pass  # a probe every few seconds is no news

        try:
            server = ThreadingHTTPServer((listener.address, listener.port), Handler)
        except OSError as err:
            what = "metrics" if listener.paths == (METRICS,) else "the health probes"
            reason = err.strerror or err
            raise SettingsError(
                f"cannot serve {what} on {listener.address}:{listener.port} ({listener.settings}): {reason}"
            ) from None
        server.daemon_threads = True
        thread = threading.Thread(target=server.serve_forever, name=f"gcdtrav-http-{listener.port}", daemon=True)
        thread.start()
        self._servers.append(server)
        self._threads.append(thread)
        base = f"http://{listener.address}:{self.port_of(server)}"
        if PROBES[0] in listener.paths:
            log.info("health probes on %s/livez and /readyz", base)
        if METRICS in listener.paths:
            log.info("metrics on %s/metrics", base)

    @staticmethod
    def port_of(server: ThreadingHTTPServer) -> int:
        return int(server.server_address[1])

    @property
    def ports(self) -> list[int]:
        return [self.port_of(server) for server in self._servers]

    def starting(self, what: str) -> None:
        """What the probes answer (503) until the service is handed over."""
        with self._lock:
            self._starting = f"starting: {what}"

    def serve(self, checks: Checks) -> None:
        """From now on the probes are the service's and /metrics its registry."""
        with self._lock:
            self._checks = checks

    def _answer(self, path: str) -> tuple[int, str, bytes]:
        with self._lock:
            checks, starting = self._checks, self._starting
        if checks is None:
            return 503, "text/plain; charset=utf-8", f"{starting}\n".encode()
        if path == METRICS:
            return 200, CONTENT_TYPE_LATEST, generate_latest(checks.registry)
        health = checks.live() if path == "/livez" else checks.ready()
        text = "ok" if health.healthy else (health.reason or "not ready")
        return (200 if health.healthy else 503), "text/plain; charset=utf-8", f"{text}\n".encode()

    def close(self) -> None:
        for server, thread in zip(self._servers, self._threads, strict=False):
            if thread.is_alive():
                server.shutdown()
            server.server_close()
        self._servers, self._threads = [], []


def not_found(paths: tuple[str, ...]) -> tuple[int, str, bytes]:
    return 404, "text/plain; charset=utf-8", f"not found: {' or '.join(paths)}\n".encode()
