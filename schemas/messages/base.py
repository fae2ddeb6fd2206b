"""The base of every message: its schema version, its errors, msgpack and JSON in and out (docs/messages.md)."""

from __future__ import annotations

import json
import re
from typing import Any, TypeVar

import msgpack
from gcdtrav.schemas.strict import WireModel, problems
from pydantic import Field, ValidationError

MSGPACK_ENCODING = "application/msgpack"
# major.minor of every message below. A minor step adds fields (older readers ignore them); a major step
# changes or removes one, and a reader refuses a message of another major with both versions named.
# 1.0 was the integer 1 in MapsHeader only; 1.1 puts the version in every message and adds risk fields;
# 1.2 adds ServiceStatus.measuring, MapsHeader.order, the status's health and anchor-set fleet fields, and the
# grid's planner layers (GridMessage, GridHeader); 1.5 adds the grid's speed layer (GridMessage.speed_png,
# GridStatus.speed_ago_s and speed_safe), RelayHealth.parked, the store's status and the anchor record (issue 46);
# 1.6 adds RelayHealth.safe_mask (the relay's own safe speed mask, issue 55).
# 1.7 adds CalibrationReport/AnchorProposal.share_by_robot and excluded_robots, the exclusions' messages (58).
SCHEMA_VERSION = "1.7"
_VERSION = re.compile(r"^(\d+)(?:\.\d+)?$")


class MessageError(ValueError):
    """A payload that is not a valid message of the expected type."""


class MessageTooLarge(MessageError):
    """A payload over the size its reader accepts: refused unread."""


def check_size(name: str, payload: bytes, max_bytes: int | None) -> None:
    """Refuse a payload of ``name`` over ``max_bytes`` before reading it (None: no limit)."""
    if max_bytes is not None and len(payload) > max_bytes:
        raise MessageTooLarge(f"{name} of {len(payload)} bytes exceeds the limit of {max_bytes}")


class SchemaVersionError(MessageError):
    """A message of another major schema version: its fields may mean something else here."""


def schema_major(version: object) -> int:
    """The major of '1.2', '1' or 1 (a 1.0 writer's integer); a MessageError for anything else."""
    match = _VERSION.match(str(version)) if isinstance(version, (int, str)) and not isinstance(version, bool) else None
    if match is None:
        raise MessageError(f"schema_version {version!r} is not 'major.minor'")
    return int(match.group(1))


def check_schema_version(name: str, version: object) -> None:
    """Accept this major with any minor (newer minors only add fields); refuse another major."""
    if schema_major(version) != schema_major(SCHEMA_VERSION):
        raise SchemaVersionError(
            f"{name} has schema version {version}, this reader reads {schema_major(SCHEMA_VERSION)}.x "
            f"(it has {SCHEMA_VERSION}): upgrade or downgrade gcdtrav on one side"
        )


class Message(WireModel):
    """A whole payload on the bus. Packed with the writer's ``schema_version``; read under the wire rule:
    unknown fields ignored, another major refused (schemas/strict.py)."""

    schema_version: str = Field(default=SCHEMA_VERSION, description="major.minor of the writer's schemas.")

    def pack(self) -> bytes:
        return msgpack.packb(self.model_dump(mode="python"), use_bin_type=True)

    @classmethod
    def unpack(cls: type[M], payload: bytes, max_bytes: int | None = None) -> M:
        check_size(cls.__name__, payload, max_bytes)
        return cls.validated(cls._msgpack_fields(payload))

    @classmethod
    def decode(cls: type[M], payload: bytes, max_bytes: int | None = None) -> M:
        """The message in msgpack, or in JSON (a payload starting with '{'), as a person or a script without
        msgpack sends it; MessageTooLarge over ``max_bytes``, MessageError naming what else is wrong."""
        return cls.validated(cls.fields(payload, max_bytes))

    @classmethod
    def fields(cls, payload: bytes, max_bytes: int | None = None) -> dict[str, Any]:
        """The payload's fields as ``decode`` reads them, not yet validated; the same errors otherwise."""
        check_size(cls.__name__, payload, max_bytes)
        if payload.lstrip()[:1] != b"{":
            return cls._msgpack_fields(payload)
        try:
            data = json.loads(payload)
        except (ValueError, UnicodeDecodeError) as err:
            raise MessageError(f"not a JSON {cls.__name__}: {err}") from None
        if not isinstance(data, dict):
            raise MessageError(f"a {cls.__name__} must be a JSON object")
        return data

    @classmethod
    def _msgpack_fields(cls, payload: bytes) -> dict[str, Any]:
        try:
            data = msgpack.unpackb(payload, raw=False, strict_map_key=True)
        except (ValueError, msgpack.UnpackException, TypeError) as err:
            raise MessageError(f"not a msgpack {cls.__name__}: {err}") from None
        if not isinstance(data, dict):
            raise MessageError(f"a {cls.__name__} must be a msgpack map, got {type(data).__name__}")
        return data

    @classmethod
    def validated(cls: type[M], data: dict[str, Any]) -> M:
        """The message from decoded fields (msgpack, or a ROS message's), or a MessageError naming the fields."""
        if "schema_version" in data:  # a 1.0 writer sent none: same major
            check_schema_version(cls.__name__, data["schema_version"])
            data = {**data, "schema_version": str(data["schema_version"])}
        try:
            return cls.model_validate(data)
        except ValidationError as err:
            raise MessageError(f"invalid {cls.__name__}: {problems(err, most=5)}") from None


M = TypeVar("M", bound=Message)


def peek_fields(payload: bytes, names: tuple[str, ...]) -> dict[str, Any]:
    """Some top-level fields of a msgpack message, skipping the others unread (a frame's pixels, a map's
    PNGs): a message's stamp at intake costs no copy of its data. Missing fields are absent; a MessageError
    if ``payload`` is not a msgpack map."""
    unpacker = msgpack.Unpacker(raw=False, strict_map_key=True, max_buffer_size=max(len(payload), 1))
    found: dict[str, Any] = {}
    try:
        unpacker.feed(payload)
        for _ in range(unpacker.read_map_header()):
            key = unpacker.unpack()
            if key in names:
                found[key] = unpacker.unpack()
                if len(found) == len(names):
                    break
            else:
                unpacker.skip()
    except (ValueError, msgpack.UnpackException, msgpack.OutOfData, TypeError) as err:
        raise MessageError(f"not a msgpack map: {type(err).__name__}: {err}") from None
    return found
