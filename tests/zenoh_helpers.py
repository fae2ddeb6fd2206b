"""Real zenoh sessions on loopback for tests: multicast scouting off, ports picked by the test."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import zenoh
from gcdtrav.client.session.zenoh_args import zenoh_config

from tools.loopback import free_port as free_port  # re-exported: tests take it from here
from tools.loopback import listening as listening  # re-exported
from tools.loopback import serve_command
from tools.loopback import waits_before_dropping as waits_before_dropping  # re-exported


def connecting_config(port: int, mode: str = "peer") -> zenoh.Config:
    conf = zenoh_config(mode=mode, connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    conf.insert_json5("scouting/gossip/enabled", "false")
    return waits_before_dropping(conf)


def wait_until(condition: Callable[[], object], timeout: float = 10.0, interval: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(interval)
    return bool(condition())


def subscribed_elsewhere(session: zenoh.Session, key: str, timeout: float = 30.0) -> bool:
    """Whether ``session`` comes to know a subscriber of ``key`` in another session within ``timeout``: what it
    publishes on ``key`` from then on reaches that subscriber. Waited for instead of sleeping while a
    subscription travels: a client's maps subscription to an in-process service's session, or a service's
    input subscription to the client's."""
    publisher = session.declare_publisher(key, allowed_destination=zenoh.Locality.REMOTE)
    try:

        def matching() -> bool:
            status = publisher.matching_status  # a MatchingStatus at runtime (the 1.x stub says bool)
            return bool(getattr(status, "matching", status))

        return wait_until(matching, timeout)
    finally:
        publisher.undeclare()


def start_router(port: int):  # type: ignore[no-untyped-def]
    """A router process on loopback; returns once it listens."""
    import subprocess
    import sys
    from pathlib import Path

    process = subprocess.Popen(
        [sys.executable, str(Path(__file__).with_name("zenoh_router.py")), str(port)], stdout=subprocess.PIPE, text=True
    )
    assert process.stdout is not None
    line = process.stdout.readline()
    assert "router ready" in line, line
    return process


def client_config(port: int) -> zenoh.Config:
    """A client-mode session of the router on ``port``: it reconnects by itself when the router returns."""
    return waits_before_dropping(
        zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    )


def serve_args(model: object, *extra: str) -> list[str]:
    """The command line of `gcdtrav serve` with this Python, multicast scouting off."""
    return serve_command("--model", str(model), "--no-multicast-scouting", *extra)


def service_reachable(client: object, timeout: float = 5.0) -> bool:
    """True once a gcdtrav service answers the client's status query. ``timeout`` only matters while a service
    is known and slow (a loaded host): with none, the query ends at once."""
    from gcdtrav.client import QueryTimeout

    try:
        client.status(timeout=timeout)  # type: ignore[attr-defined]
        return True
    except QueryTimeout:
        return False


def input_subscribed(client: object, source: str, timeout: float = 30.0) -> bool:
    """Whether the client's session comes to know the service's subscription to ``source``'s images within
    ``timeout``: an image the client publishes from then on reaches the service (an in-process one or a
    `gcdtrav serve` subprocess alike)."""
    from gcdtrav.schemas.keys import input_key

    return subscribed_elsewhere(client.session, input_key(client.input_prefix, source), timeout)  # type: ignore[attr-defined]


class MapsInbox:
    """The maps of ``selector``, subscribed now (unlike ``iter_maps``, a generator that subscribes only at its
    first ``next``): declared before the client publishes an image, the subscription reaches the service
    ahead of that image (zenoh sends a session's declarations ahead of its later data), so the service knows
    it when it publishes the image's maps."""

    def __init__(self, client: object, selector: str = "**") -> None:
        import queue

        self._inbox: queue.Queue[object] = queue.Queue()
        self._subscriber = client.subscribe_maps(selector, self._inbox.put)  # type: ignore[attr-defined]

    def next(self, timeout: float = 60.0):  # type: ignore[no-untyped-def]
        """The next maps, waiting up to ``timeout`` (a failure's bound, not a measure): AssertionError if none."""
        import queue

        try:
            return self._inbox.get(timeout=timeout)
        except queue.Empty:
            raise AssertionError(f"no maps within {timeout} s") from None

    def close(self) -> None:
        self._subscriber.undeclare()


def first_frame_through(
    client: object, source: str, image: object, timeout: float = 60.0, stamp: float | None = None
) -> None:
    """Wait for the service, send one image as ``source`` (stamped ``stamp``, else bare), wait for its maps: the
    service has a frame. Nothing here waits for time: the image is published once the service's input
    subscription is known to the client, and the maps subscription is declared before it (``MapsInbox``)."""
    assert wait_until(lambda: service_reachable(client), timeout), "the service did not answer"
    inbox = MapsInbox(client, source)
    try:
        assert input_subscribed(client, source, timeout), "the service's input subscription never reached the client"
        client.publish_image(source, image, stamp=stamp)  # type: ignore[attr-defined]
        inbox.next(timeout)
    finally:
        inbox.close()
    # The maps go out just before the frame is counted: wait for the count too, so that
    # a status query right after this sees the frame even on a loaded machine.
    assert wait_until(lambda: frame_counted(client, source), timeout), "the frame was not counted"


def frame_counted(client: object, source: str) -> bool:
    """True once some instance's status counts a processed frame of ``source``."""
    from gcdtrav.client import QueryTimeout

    try:
        statuses = client.statuses(timeout=5.0)  # type: ignore[attr-defined]
    except QueryTimeout:  # no instance answered in time (a loaded host): not yet
        return False
    return any(source in s.sources and s.sources[source].processed > 0 for s in statuses)


@dataclass
class FakePayload:
    data: bytes

    def to_bytes(self) -> bytes:
        return self.data

    def __len__(self) -> int:
        return len(self.data)


@dataclass
class FakeSample:
    """What a zenoh callback reads of a sample, to call the callback directly."""

    payload: FakePayload
    key_expr: str = ""


def fake_sample(data: bytes, key_expr: str = "") -> FakeSample:
    return FakeSample(FakePayload(data), key_expr)
