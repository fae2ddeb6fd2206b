"""A batch the store committed but whose answer was lost is replayed by the outbox and stored nothing twice
(issue 57 item 4): a real PostgreSQL behind a loopback TCP proxy that, once armed, forwards the client's COMMIT
and then cuts the connection before the server's answer reaches the client, as a link that drops at the worst
moment. Before batch ids, the outbox wrote the batch again and the store held it twice."""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import Iterator

import pytest
from gcdtrav.service.store.outbox import PairOutbox
from gcdtrav.service.store.postgres import PostgresStore
from postgres_cluster import PostgresCluster, postgres_cluster
from store_test_helpers import pair

GRASS = ("grass", "gravel", "rock")


class LostAnswerProxy:
    """Loopback TCP between a client and PostgreSQL; ``arm()``: the next COMMIT reaches the server, its answer
    never the client (both connections are cut the moment the server answers)."""

    def __init__(self, target_port: int) -> None:
        self.target_port, self.port = target_port, 0
        self.armed = threading.Event()
        self.cut = 0
        self._loop = asyncio.new_event_loop()
        self._server: asyncio.Server | None = None
        self._thread = threading.Thread(target=self._loop.run_forever, daemon=True)

    def start(self) -> LostAnswerProxy:
        self._thread.start()
        asyncio.run_coroutine_threadsafe(self._listen(), self._loop).result(10)
        return self

    def arm(self) -> None:
        self.armed.set()

    def stop(self) -> None:
        if self._server is not None:
            self._loop.call_soon_threadsafe(self._server.close)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(10)

    async def _listen(self) -> None:
        self._server = await asyncio.start_server(self._connection, "127.0.0.1", 0)
        self.port = int(self._server.sockets[0].getsockname()[1])

    async def _connection(self, client_reader: asyncio.StreamReader, client_writer: asyncio.StreamWriter) -> None:
        server_reader, server_writer = await asyncio.open_connection("127.0.0.1", self.target_port)
        committed = asyncio.Event()

        async def up() -> None:
            while chunk := await client_reader.read(65536):
                server_writer.write(chunk)
                await server_writer.drain()
                if self.armed.is_set() and b"COMMIT" in chunk.upper():
                    self.armed.clear()
                    committed.set()

        async def down() -> None:
            while chunk := await server_reader.read(65536):
                if committed.is_set():  # the server's answer to the COMMIT: lost with the connection
                    self.cut += 1
                    break
                client_writer.write(chunk)
                await client_writer.drain()

        tasks = [asyncio.ensure_future(up()), asyncio.ensure_future(down())]
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        for task in tasks:
            task.cancel()
        for writer in (client_writer, server_writer):
            with contextlib.suppress(Exception):
                writer.close()


@pytest.fixture
def own_cluster() -> Iterator[PostgresCluster]:
    with postgres_cluster() as running:
        yield running


def test_a_batch_replayed_after_its_lost_commit_answer_is_stored_once(own_cluster: PostgresCluster) -> None:
    url = own_cluster.create_database("replay")
    proxy = LostAnswerProxy(own_cluster.port).start()
    through_proxy = url.replace(f":{own_cluster.port}/", f":{proxy.port}/")
    outbox = PairOutbox(
        lambda: PostgresStore(through_proxy, own_cluster.password, connect_timeout_s=2),
        "postgresql", through_proxy, 100_000, max_pairs=10**6, max_bytes=10**9, retry_s=0.2,
    )  # fmt: skip
    reader = PostgresStore(url, own_cluster.password)  # straight to the server: what it really holds
    try:
        assert outbox.open_now() is not None
        outbox.start()
        outbox.put([pair(GRASS, k) for k in range(40)])  # a first batch, committed and answered
        assert outbox.flush(30) and len(reader.pairs(GRASS)) == 40
        proxy.arm()
        outbox.put([pair(GRASS, 100 + k) for k in range(60)])
        assert outbox.flush(60), outbox.state()
        assert proxy.cut == 1, "the proxy never cut a COMMIT's answer"
        stamps = sorted(reader.pairs(GRASS).stamps.tolist())
        assert len(stamps) == 100 and len(set(stamps)) == 100, f"{len(stamps)} pairs stored for 100 put"
        assert outbox.state().written == 100 and outbox.state().pending == 0
    finally:
        outbox.close()
        reader.close()
        proxy.stop()
