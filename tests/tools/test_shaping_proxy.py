"""The link-shaping proxy: lower bounds of time only (a slow machine only makes them larger)."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import pytest

from tools.shaping_proxy import LinkShape, shaping_proxy


@contextmanager
def echo_server() -> Iterator[int]:
    """A TCP server on 127.0.0.1 that sends back what it receives."""
    listener = socket.create_server(("127.0.0.1", 0))
    stop = threading.Event()

    def serve() -> None:
        listener.settimeout(0.2)
        while not stop.is_set():
            try:
                conn, _ = listener.accept()
            except TimeoutError:
                continue
            threading.Thread(target=echo, args=(conn,), daemon=True).start()

    def echo(conn: socket.socket) -> None:
        with conn:
            while data := conn.recv(65536):
                conn.sendall(data)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield int(listener.getsockname()[1])
    finally:
        stop.set()
        thread.join(5)
        listener.close()


def round_trip(port: int, payload: bytes, timeout: float = 60.0) -> float:
    """Seconds to send ``payload`` through the proxy and read all of it back."""
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as conn:
        began = time.monotonic()
        sender = threading.Thread(target=conn.sendall, args=(payload,), daemon=True)
        sender.start()
        received = 0
        while received < len(payload):
            chunk = conn.recv(65536)
            assert chunk, "the proxy closed the connection"
            received += len(chunk)
        sender.join(timeout)
        return time.monotonic() - began


def test_bandwidth_bounds_the_bytes_per_second() -> None:
    with echo_server() as port, shaping_proxy(port, LinkShape(rate_bps=1e6)) as proxy:
        elapsed = round_trip(proxy.port, b"x" * 100_000)
        up, down = proxy.delivered()
    # 100 kB at 1 Mbit/s (125 kB/s) take 0.8 s, less one burst of 16 kB; echoed, both directions are shaped.
    assert elapsed >= 0.5
    assert elapsed < 30  # an order of magnitude, not a timing
    assert (up, down) == (100_000, 100_000)


def test_delay_holds_every_byte_each_way() -> None:
    with echo_server() as port, shaping_proxy(port, LinkShape(rate_bps=100e6, delay_s=0.15)) as proxy:
        elapsed = round_trip(proxy.port, b"ping")
    assert elapsed >= 0.3  # 0.15 s up, 0.15 s back


def test_an_outage_stops_the_bytes_until_the_link_returns() -> None:
    with echo_server() as port, shaping_proxy(port, LinkShape(rate_bps=100e6)) as proxy:
        assert round_trip(proxy.port, b"before") < 30
        proxy.outage()
        threading.Timer(0.5, proxy.outage, kwargs={"down": False}).start()
        assert round_trip(proxy.port, b"during") >= 0.4


@pytest.mark.parametrize("shape", [dict(rate_bps=0), dict(rate_bps=1e6, delay_s=-1), dict(rate_bps=1e6, burst_bytes=0)])
def test_a_link_needs_a_rate_and_a_delay(shape: dict[str, float]) -> None:
    with pytest.raises(ValueError, match="positive rate"):
        LinkShape(**shape)  # type: ignore[arg-type]
