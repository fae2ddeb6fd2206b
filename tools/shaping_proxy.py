"""A TCP proxy that behaves like a slow radio link: bandwidth, one-way delay, outages. No root, no tc.

    python -m tools.shaping_proxy --listen 7448 --target 127.0.0.1:7447 --mbit 2 --delay-ms 50

Each direction of each connection has its own token bucket (``rate_bps``, a burst of ``burst_bytes``) and
delay line: a chunk is read only when the bucket holds its bytes, then delivered ``delay_s`` later, so what
the far end sees is at most the rate, the delay after it was sent. What waits for the bucket stays in the
kernel's socket buffers, which the proxy keeps small (``socket_buffer_bytes``), like a radio's queue. An
outage (``outage()``) stops both directions of every connection: nothing is read or delivered until the link
returns, as a Wi-Fi drop that TCP rides out (or a lease that expires).

The zenoh sessions on either side must not use shared memory: ``transport/shared_memory/enabled: false``
on both ends, or large payloads between processes of one host bypass the proxy.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass

CHUNK_BYTES = 16 * 1024


@dataclass(frozen=True)
class LinkShape:
    rate_bps: float  # bits per second, each direction
    delay_s: float = 0.0  # one way
    burst_bytes: int = CHUNK_BYTES
    socket_buffer_bytes: int = 64 * 1024

    def __post_init__(self) -> None:
        if not self.rate_bps > 0 or self.delay_s < 0 or self.burst_bytes < 1:
            raise ValueError(f"a link needs a positive rate and burst and a delay >= 0: {self}")


class TokenBucket:
    """``rate`` bytes per second, at most ``burst`` at once; ``take`` waits until the bytes are there."""

    def __init__(self, rate: float, burst: int) -> None:
        self.rate, self.burst = rate, burst
        self._tokens = float(burst)
        self._at = time.monotonic()

    async def take(self, nbytes: int) -> None:
        while True:
            now = time.monotonic()
            self._tokens = min(self.burst, self._tokens + (now - self._at) * self.rate)
            self._at = now
            if self._tokens >= nbytes:
                self._tokens -= nbytes
                return
            await asyncio.sleep((nbytes - self._tokens) / self.rate)


@dataclass
class Counters:
    up: int = 0  # bytes client -> target
    down: int = 0  # bytes target -> client
    connections: int = 0


class ShapingProxy:
    """Run on its own event-loop thread: ``with shaping_proxy(...) as proxy`` or ``start()`` / ``stop()``."""

    def __init__(self, target: tuple[str, int], shape: LinkShape, listen_port: int = 0) -> None:
        self.target, self.shape = target, shape
        self.counters = Counters()
        self.port = listen_port
        self._loop = asyncio.new_event_loop()
        self._link_up = asyncio.Event()
        self._server: asyncio.Server | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._thread = threading.Thread(target=self._loop.run_forever, name="shaping-proxy", daemon=True)

    # ---- control, from any thread ---------------------------------------------------------------------
    def start(self) -> ShapingProxy:
        self._thread.start()
        asyncio.run_coroutine_threadsafe(self._listen(), self._loop).result(10)
        return self

    def stop(self) -> None:
        asyncio.run_coroutine_threadsafe(self._close(), self._loop).result(10)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(10)
        self._loop.close()

    def outage(self, down: bool = True) -> None:
        """Stop (``down``) or resume every byte, both directions."""
        self._loop.call_soon_threadsafe(self._link_up.clear if down else self._link_up.set)

    def delivered(self) -> tuple[int, int]:
        """(up, down) bytes delivered so far."""
        return self.counters.up, self.counters.down

    # ---- the loop -------------------------------------------------------------------------------------
    async def _listen(self) -> None:
        self._link_up.set()
        self._server = await asyncio.start_server(self._connection, "127.0.0.1", self.port)
        self.port = int(self._server.sockets[0].getsockname()[1])

    async def _close(self) -> None:
        if self._server is not None:
            self._server.close()
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)

    async def _connection(self, client_reader: asyncio.StreamReader, client_writer: asyncio.StreamWriter) -> None:
        self.counters.connections += 1
        try:
            target_reader, target_writer = await asyncio.open_connection(*self.target)
        except OSError:
            client_writer.close()
            return
        for writer in (client_writer, target_writer):
            self._small_buffers(writer)
        pumps = [
            asyncio.ensure_future(self._pump(client_reader, target_writer, "up")),
            asyncio.ensure_future(self._pump(target_reader, client_writer, "down")),
        ]
        self._tasks.update(pumps)
        try:
            await asyncio.wait(pumps, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for pump in pumps:
                pump.cancel()
                self._tasks.discard(pump)
            for writer in (client_writer, target_writer):
                writer.close()

    def _small_buffers(self, writer: asyncio.StreamWriter) -> None:
        sock = writer.get_extra_info("socket")
        if sock is not None:
            for option in (socket.SO_RCVBUF, socket.SO_SNDBUF):
                sock.setsockopt(socket.SOL_SOCKET, option, self.shape.socket_buffer_bytes)
        writer.transport.set_write_buffer_limits(high=self.shape.socket_buffer_bytes)

    async def _pump(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, direction: str) -> None:
        """Read what the bucket allows, deliver it ``delay_s`` later; the delay line holds rate x delay bytes."""
        bucket = TokenBucket(self.shape.rate_bps / 8, self.shape.burst_bytes)
        line: asyncio.Queue[tuple[float, bytes]] = asyncio.Queue()
        deliver = asyncio.ensure_future(self._deliver(line, writer, direction))
        try:
            while True:
                await self._link_up.wait()
                data = await reader.read(min(CHUNK_BYTES, self.shape.burst_bytes))
                if not data:
                    break
                await bucket.take(len(data))
                line.put_nowait((time.monotonic() + self.shape.delay_s, data))
            line.put_nowait((0.0, b""))
            await deliver
        finally:
            deliver.cancel()

    async def _deliver(self, line: asyncio.Queue[tuple[float, bytes]], writer: asyncio.StreamWriter, way: str) -> None:
        while True:
            due, data = await line.get()
            if not data:
                return
            await asyncio.sleep(max(0.0, due - time.monotonic()))
            await self._link_up.wait()
            if way == "up":  # counted as handed to the far end's socket, before it can be read there
                self.counters.up += len(data)
            else:
                self.counters.down += len(data)
            writer.write(data)
            await writer.drain()


@contextlib.contextmanager
def shaping_proxy(target_port: int, shape: LinkShape, target_host: str = "127.0.0.1") -> Iterator[ShapingProxy]:
    """A started proxy to ``target_host:target_port`` on a free port of 127.0.0.1 (``proxy.port``)."""
    proxy = ShapingProxy((target_host, target_port), shape).start()
    try:
        yield proxy
    finally:
        proxy.stop()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--listen", type=int, required=True, help="port on 127.0.0.1")
    parser.add_argument("--target", required=True, help="HOST:PORT")
    parser.add_argument("--mbit", type=float, required=True, help="Mbit/s each way")
    parser.add_argument("--delay-ms", type=float, default=0.0, help="one-way delay, ms")
    args = parser.parse_args()
    host, _, port = args.target.rpartition(":")
    proxy = ShapingProxy((host, int(port)), LinkShape(args.mbit * 1e6, args.delay_ms / 1e3), args.listen).start()
    print(f"shaping 127.0.0.1:{proxy.port} -> {args.target}: {args.mbit} Mbit/s, {args.delay_ms} ms", flush=True)
    with contextlib.suppress(KeyboardInterrupt):
        threading.Event().wait()
    proxy.stop()


if __name__ == "__main__":
    main()
