"""The metrics port of `gcdtrav serve`: prometheus_client's HTTP server over the service's registry
(service/runtime/metrics.py), on ``metrics_address:metrics_port``; ``metrics_port: 0``: nothing listens."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager

from gcdtrav.schemas.settings import ServiceSettings, SettingsError
from prometheus_client import CollectorRegistry, start_http_server

log = logging.getLogger("gcdtrav.service")


@contextmanager
def metrics_endpoint(settings: ServiceSettings, registry: CollectorRegistry) -> Iterator[str | None]:
    """Serve ``registry`` on GET /metrics while the context runs; yields the URL, or None when off."""
    if settings.metrics_port == 0:
        yield None
        return
    address, port = settings.metrics_address, settings.metrics_port
    try:
        server, thread = start_http_server(port, address, registry=registry)
    except OSError as err:
        raise SettingsError(f"cannot serve metrics on {address}:{port} (metrics_port): {err.strerror or err}") from None
    url = f"http://{address}:{port}/metrics"
    log.info("metrics on %s", url)
    try:
        yield url
    finally:
        server.shutdown()
        server.server_close()
        thread.join(5)
