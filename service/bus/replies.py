"""Replies in msgpack by default, in JSON when the selector says ``format=json`` (any case: ``format=JSON``).

zenoh's own tools print what they get: ``z_get -s 'gcdtrav/status?format=json'`` from zenoh-python's
examples and the router's REST plugin (``curl 'http://router:8000/gcdtrav/status?format=json'``) show JSON
that people can read, where msgpack is binary. Every queryable answers through these helpers, errors too.
"""

from __future__ import annotations

import zenoh
from gcdtrav.schemas.messages import MSGPACK_ENCODING, Message
from gcdtrav.service.runtime.errors import QueryError

MSGPACK = zenoh.Encoding(MSGPACK_ENCODING)
JSON = zenoh.Encoding.APPLICATION_JSON
FORMATS = ("msgpack", "json")


def parameters(query: zenoh.Query) -> list[tuple[str, str]]:
    """The selector's (name, value) pairs, repeats included."""
    return [(name, value) for name, value in query.parameters]  # type: ignore[attr-defined]


def formats(query: zenoh.Query) -> list[str]:
    """The selector's ``format`` values, lower case: people type ``format=JSON`` too."""
    return [value.lower() for name, value in parameters(query) if name == "format"]


def wants_json(query: zenoh.Query) -> bool:
    """Whether the selector asks for JSON; an unknown format falls back to msgpack (and is reported)."""
    return "json" in formats(query)


def check_format(query: zenoh.Query) -> None:
    asked = formats(query)
    if len(asked) > 1 or (asked and asked[0] not in FORMATS):
        given = ";".join(f"{name}={value}" for name, value in parameters(query) if name == "format")
        raise QueryError(f"{given}: give format=json or format=msgpack once [msgpack]")


def check_no_parameters(query: zenoh.Query) -> None:
    """Keys that take nothing but ``format`` (status, the anchor set, its history) say so, not ignore the rest."""
    check_format(query)
    others = sorted({name for name, _ in without_format(query)})
    if others:
        raise QueryError(f"unknown parameter(s) {others}; this key takes only format=json or format=msgpack")


def without_format(query: zenoh.Query) -> list[tuple[str, str]]:
    """The selector's parameters less ``format``, for the handlers that parse the rest strictly."""
    return [(name, value) for name, value in parameters(query) if name != "format"]


def text_without_format(text: str) -> str:
    """'x=1;format=json;y=2' -> 'x=1;y=2', keeping a path's own ';' separators."""
    return ";".join(part for part in text.split(";") if not part.startswith("format="))


def encoded(query: zenoh.Query, message: Message) -> tuple[bytes, zenoh.Encoding]:
    if wants_json(query):
        return message.model_dump_json().encode("utf-8"), JSON
    return message.pack(), MSGPACK


def reply(query: zenoh.Query, key: str, message: Message) -> None:
    payload, encoding = encoded(query, message)
    query.reply(key, payload, encoding=encoding)


def reply_error(query: zenoh.Query, message: Message) -> None:
    payload, encoding = encoded(query, message)
    query.reply_err(payload, encoding=encoding)
