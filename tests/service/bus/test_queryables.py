"""The query handlers with a stand-in for zenoh's Query: what they answer, and that every query is answered,
also when the answer itself raises on the anchor switch's thread."""

from __future__ import annotations

import logging
import threading
from typing import Any

import msgpack
import numpy as np
import pytest
from gcdtrav.schemas.anchors import AnchorSet, default_anchor_set
from gcdtrav.schemas.keys import Keys
from gcdtrav.schemas.messages import AnchorHistoryEntry, ContextDistribution, ErrorReply
from gcdtrav.service.bus import queryables, replies
from gcdtrav.service.bus.guard import answering
from gcdtrav.service.runtime.history import FrameHistory
from gcdtrav.service.runtime.stats import ServiceStats

KEYS = Keys("gcdtrav")
ANCHORS = default_anchor_set()


class Payload(bytes):
    """zenoh's ZBytes, as far as the handlers use it."""

    def to_bytes(self) -> bytes:
        return bytes(self)


class FakeQuery:
    """What the handlers read of a zenoh.Query, and what they send back."""

    def __init__(self, key: str, parameters: str = "", payload: bytes | None = None) -> None:
        self.key_expr, self.selector = key, f"{key}?{parameters}"
        self.payload = Payload(payload) if payload is not None else None
        self.parameters = [tuple(part.split("=", 1)) for part in parameters.split(";") if part]
        self.replies: list[tuple[str, bytes]] = []
        self.errors: list[bytes] = []
        self.answered = threading.Event()

    def reply(self, key: str, payload: bytes, encoding: Any = None) -> None:
        self.replies.append((key, payload))
        self.answered.set()

    def reply_err(self, payload: bytes, encoding: Any = None) -> None:
        self.errors.append(payload)
        self.answered.set()

    def drop(self) -> None:
        """An answer sent later drops the query: the querier learns no more replies come."""
        self.dropped = True


def wait_for_drop(query: FakeQuery) -> bool:
    import time

    deadline = time.monotonic() + 5
    while not getattr(query, "dropped", False) and time.monotonic() < deadline:
        time.sleep(0.01)
    return getattr(query, "dropped", False)


def history_with_a_frame() -> FrameHistory:
    history = FrameHistory(2)
    weights = np.full((len(ANCHORS), 4, 6), 1 / len(ANCHORS), np.float32)
    history.record("r1/front", weights, ANCHORS, 5.0, "cam", (60, 40))
    return history


@pytest.fixture
def stats() -> ServiceStats:
    return ServiceStats(logging.getLogger("test"))


def test_a_patch_query_answers_the_patch_of_a_pixel(stats: ServiceStats) -> None:
    handlers = queryables.SourceQueries(KEYS, history_with_a_frame(), None, lambda source: True)
    query = FakeQuery(KEYS.patch("r1/front"), "x=59;y=0")
    answering(handlers.on_patch, stats)(query)  # type: ignore[arg-type]
    reply = ContextDistribution.unpack(query.replies[0][1])
    assert reply.patch == (0, 5) and reply.seq == 0 and reply.mean == pytest.approx(np.mean(ANCHORS.positions))


def test_a_patch_query_for_a_source_another_instance_owns_is_left_to_it(stats: ServiceStats) -> None:
    handlers = queryables.SourceQueries(KEYS, history_with_a_frame(), None, lambda source: False)
    query = FakeQuery(KEYS.patch("r1/front"), "x=1;y=1")
    answering(handlers.on_patch, stats)(query)  # type: ignore[arg-type]
    assert not query.replies and not query.errors


@pytest.mark.parametrize(
    ("parameters", "error"),
    [("x=1", "give exactly one of"), ("x=1;y=1;x=2", "more than once"), ("x=999;y=1", "outside the 60x40 image")],
)
def test_a_bad_patch_query_is_answered_with_its_error(stats: ServiceStats, parameters: str, error: str) -> None:
    handlers = queryables.SourceQueries(KEYS, history_with_a_frame(), None, lambda source: True)
    query = FakeQuery(KEYS.patch("r1/front"), parameters)
    answering(handlers.on_patch, stats)(query)  # type: ignore[arg-type]
    assert error in ErrorReply.unpack(query.errors[0]).error
    assert stats.snapshot({}).rejected_by_reason == {"bad_query": 1}


class ImmediateSwitch:
    """Reports a swap at once, from another thread, as the AnchorSwitch's worker does."""

    instance = "box-1"

    def submit(self, body: bytes, done: Any, expected: str | None = None) -> None:
        anchors = AnchorSet.from_text(body, source="test")
        threading.Thread(target=done, args=(anchors, None)).start()

    def head(self) -> AnchorHistoryEntry:
        return AnchorHistoryEntry(accepted_at=0.0, version=ANCHORS.version, anchor_set=ANCHORS)


def test_a_swap_reply_that_raises_still_answers_the_query(stats: ServiceStats, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    handlers = queryables.AnchorQueries(KEYS, ImmediateSwitch(), stats)  # type: ignore[arg-type]
    real_reply = replies.reply

    def broken(query: Any, key: str, message: Any) -> None:
        if key == KEYS.anchors:
            raise RuntimeError("the reply could not be encoded")
        real_reply(query, key, message)

    monkeypatch.setattr(replies, "reply", broken)
    query = FakeQuery(KEYS.anchors, "", ANCHORS.to_json().encode())
    answering(handlers.on_anchors, stats)(query)  # type: ignore[arg-type]
    assert query.answered.wait(5), "the swap's query was never answered"
    assert wait_for_drop(query), "an answer sent later must drop the query"
    assert "internal error: RuntimeError" in msgpack.unpackb(query.errors[0])["error"]
    assert stats.snapshot({}).rejected_by_reason == {"query_failed": 1}
