"""A query nothing answers says what happened: ended at once by zenoh, or timed out; never 'within 5 s' after 1 s."""

from __future__ import annotations

import threading
import time

import pytest
import zenoh
from gcdtrav.client import QueryTimeout, TraversabilityClient
from gcdtrav.client.client import no_reply_message, zenoh_timeout
from gcdtrav.client.session.zenoh_args import zenoh_config
from zenoh_helpers import connecting_config, free_port, wait_until


def test_a_query_ended_early_does_not_claim_the_whole_timeout() -> None:
    assert "within" not in no_reply_message("gcdtrav/status", 5.0, 1.2)
    assert "ended after 1.2 s" in no_reply_message("gcdtrav/status", 5.0, 1.2)
    assert "within 5 s" in no_reply_message("gcdtrav/status", 5.0, 5.0)


def test_no_service_on_loopback_names_what_really_happened() -> None:
    config = zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{free_port()}"], multicast_scouting=False)
    with TraversabilityClient(config=config, timeout=5.0) as client:
        started = time.monotonic()
        with pytest.raises(QueryTimeout) as raised:
            client.status()
        waited = time.monotonic() - started
    message = str(raised.value)
    # The client times the query inside this wait, so what it says is at most what was seen here (a loaded
    # machine may stretch the time around the query: compared with the client's own figure, not the window).
    if "within 5 s" in message:
        assert waited >= 4.5, (waited, message)  # it waited (nearly) the whole timeout
    else:
        said = float(message.split("the query ended after ")[1].split(" s)")[0])
        assert said < 4.5 and said <= waited + 0.05, (waited, message)  # .1f rounding


def test_a_service_too_busy_to_answer_in_time_is_a_timeout_not_a_service_error() -> None:
    """Zenoh ends a query whose queryable was reached but did not answer in time with its own error reply
    ("Timeout"): the client says QueryTimeout, as for no service at all, not ServiceError "error reply"."""
    port = free_port()
    listening = zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    release = threading.Event()
    with zenoh.open(listening) as service:
        busy = service.declare_queryable("gcdtrav/status", lambda query: release.wait(10))
        try:
            with TraversabilityClient(config=connecting_config(port), timeout=0.5) as client:
                assert wait_until(lambda: queryable_known(client.session), 30)
                with pytest.raises(QueryTimeout, match=r"within 0\.5 s"):
                    client.status()
        finally:
            release.set()
            busy.undeclare()


def queryable_known(session: zenoh.Session) -> bool:
    """Whether the session's queries of the status reach the busy queryable (a querier's matching status)."""
    querier = session.declare_querier("gcdtrav/status")
    try:
        return bool(querier.matching_status.matching)
    finally:
        querier.undeclare()


class FakeReplyError:
    """A zenoh ReplyError's two fields the client reads."""

    def __init__(self, payload: bytes, encoding: str) -> None:
        self.payload, self.encoding = zenoh.ZBytes(payload), zenoh.Encoding(encoding)


@pytest.mark.parametrize(
    ("payload", "encoding", "timed_out"),
    [
        (b"Timeout", "zenoh/string", True),  # the querying session's own timer
        (b"Timeout", "zenoh/bytes", True),  # a routing session's QueryCleanup (the default encoding), loaded
        (b"Timeout", "application/msgpack", False),  # a replier's own error, whatever it says
        (b"timeout", "zenoh/string", False),
    ],
)
def test_zenoh_s_timeouts_from_either_side_are_timeouts(payload: bytes, encoding: str, timed_out: bool) -> None:
    assert zenoh_timeout(FakeReplyError(payload, encoding)) is timed_out  # type: ignore[arg-type]
