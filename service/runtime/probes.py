"""HTTP probes for a supervisor (Kubernetes' kubelet): ``/livez`` and ``/readyz``. No middleware here.

Each answer is read from memory (no zenoh round trip, no model call), so a probe every few seconds costs
nothing and cannot fail because a router is away: 200 with ``ok``, or 503 with the reason, one line.
*Live*: the worker progresses (``progress.py``; a stalled one is restarted once the kubelet gives up).
*Ready*: the instance is in the fleet and serving (not starting, not stalled, not draining): a rolling
upgrade waits for it before it stops the next old pod.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

from gcdtrav.schemas.settings import SettingsError
from gcdtrav.service.runtime.progress import Health

log = logging.getLogger("gcdtrav.service")


def ready(health: Health, draining: bool, in_fleet: bool) -> Health:
    """The readiness rule: not draining, the worker progressing, and a member of the fleet."""
    if draining:
        return Health(False, "draining: left the fleet, finishing the frame in flight")
    if not health.healthy:
        return health
    if not in_fleet:
        return Health(False, "starting: not in the fleet yet")
    return health


class Probes:
    """``/livez`` and ``/readyz`` on ``address:port`` (port 0 in tests: one the system picks)."""

    def __init__(self, live: Callable[[], Health], ready: Callable[[], Health], address: str, port: int) -> None:
        checks = {"/livez": live, "/readyz": ready}

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                check = checks.get(self.path.split("?", 1)[0])
                if check is None:
                    status, text = 404, "not found: /livez or /readyz"
                else:
                    health = check()
                    status, text = (200, "ok") if health.healthy else (503, health.reason or "not ready")
                body = f"{text}\n".encode()
                self.send_response(status)
                self.send_header("Content-Type", "text/plain; charset=utf-8")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, format: str, *args: object) -> None:
                pass  # a probe every few seconds is no news

        try:
            self._server = ThreadingHTTPServer((address, port), Handler)
        except OSError as err:
            raise SettingsError(f"cannot listen for the health probes on {address}:{port}: {err}") from None
        self._server.daemon_threads = True
        self._thread = threading.Thread(target=self._server.serve_forever, name="gcdtrav-probes", daemon=True)

    @property
    def port(self) -> int:
        return int(self._server.server_address[1])

    def start(self) -> None:
        self._thread.start()
        log.info("health probes on http://%s:%d/livez and /readyz", self._server.server_address[0], self.port)

    def close(self) -> None:
        if self._thread.is_alive():
            self._server.shutdown()
        self._server.server_close()
