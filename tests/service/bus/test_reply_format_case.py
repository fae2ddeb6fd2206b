"""`format=JSON` (any case) answers JSON, as `format=json` does: zenoh's own tools (z_get, the REST plugin)
print JSON and fail on msgpack, so a capital letter must not turn a readable answer into a crash."""

from __future__ import annotations

import json
from collections.abc import Iterator

import msgpack
import pytest
import zenoh
from gcdtrav.client.session.zenoh_args import zenoh_config
from gcdtrav.schemas.messages import ErrorReply
from gcdtrav.service.bus import replies
from gcdtrav.service.runtime.errors import QueryError

KEY = "test/replies/status"


def answer(query: zenoh.Query) -> None:
    """Like the status key: only format, answered through the replies helpers, errors too."""
    try:
        replies.check_no_parameters(query)
    except QueryError as err:
        replies.reply_error(query, ErrorReply(error=str(err)))
        return
    replies.reply(query, KEY, ErrorReply(error="not an error: the reply under test"))


@pytest.fixture(scope="module")
def session() -> Iterator[zenoh.Session]:
    config = zenoh_config(mode="peer", multicast_scouting=False)
    config.insert_json5("listen/endpoints", "[]")
    with zenoh.open(config) as opened:
        queryable = opened.declare_queryable(KEY, answer)
        yield opened
        queryable.undeclare()


def get(session: zenoh.Session, selector: str) -> tuple[bool, bytes, str]:
    (reply,) = list(session.get(selector, timeout=5.0))
    sample = reply.ok if reply.ok is not None else reply.err
    return reply.ok is not None, sample.payload.to_bytes(), str(sample.encoding)


@pytest.mark.parametrize("value", ["json", "JSON", "Json"])
def test_format_json_in_any_case_answers_json(session: zenoh.Session, value: str) -> None:
    ok, payload, encoding = get(session, f"{KEY}?format={value}")
    assert ok and encoding == "application/json"
    assert json.loads(payload)["error"].startswith("not an error")


@pytest.mark.parametrize("value", ["msgpack", "MSGPACK"])
def test_format_msgpack_in_any_case_answers_msgpack(session: zenoh.Session, value: str) -> None:
    ok, payload, _ = get(session, f"{KEY}?format={value}")
    assert ok and msgpack.unpackb(payload)["error"].startswith("not an error")


def test_errors_follow_the_format_in_any_case_and_quote_it_as_given(session: zenoh.Session) -> None:
    ok, payload, encoding = get(session, f"{KEY}?format=JSON;x=1")
    assert not ok and encoding == "application/json"
    assert json.loads(payload)["error"].startswith("unknown parameter(s) ['x']")
    ok, payload, _ = get(session, f"{KEY}?format=JSON;format=Msgpack")
    assert not ok and json.loads(payload)["error"].startswith("format=JSON;format=Msgpack: give format=json")
