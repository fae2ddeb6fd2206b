"""Every wire shape in ``gcdtrav.schemas.messages`` encodes to the same bytes as the table below says: moving a
class between modules (schemas/messages/ was one 700-line file until issue 50) must not change a byte on the
wire, and a field changed by accident shows here by name.

Each shape is filled by its annotations (every field set, none left to its default), packed as msgpack, and
its SHA-256 compared with ``ENCODINGS``. The table was printed by this file (``python
tests/schemas/test_message_encodings.py``) on the single-module schemas/messages.py of commit a055777, before
the split. A field added on purpose changes its shape's hash: print the table again and replace the rows that
changed (bump ``SCHEMA_VERSION``'s minor, docs/messages.md); ``schema_version`` itself is filled with a fixed
value, so a version bump alone changes no row.
"""

from __future__ import annotations

import hashlib
import inspect
import types
import typing
from enum import Enum
from typing import Any

import annotated_types
import msgpack
from gcdtrav.schemas import messages
from gcdtrav.schemas.anchors import AnchorSet, default_anchor_set
from gcdtrav.schemas.strict import WireModel
from pydantic import BaseModel

# The public names `from gcdtrav.schemas.messages import X` gives, as the single module had them.
NAMES = (
    "AnchorHistoryEntry",
    "AnchorHistoryReply",
    "AnchorPoint",
    "AnchorSetRejection",
    "AnchorSetReply",
    "CameraParked",  # 1.5 (issue 47)
    "CameraPlacement",
    "CompactMapsMessage",
    "ContextDistribution",
    "CreditGrant",
    "ErrorReply",
    "ExperienceStatus",
    "GridCameraStatus",
    "GridHeader",
    "GridMessage",
    "GridStatus",
    "ImageEnvelope",
    "M",
    "MSGPACK_ENCODING",
    "MapsHeader",
    "MapsMessage",
    "Message",
    "MessageError",
    "MessageTooLarge",
    "PathReply",
    "PixelEncoding",
    "Pose2D",
    "QuestionStatus",
    "RAW_CHANNELS",
    "RelayHealth",
    "SCHEMA_VERSION",
    "SchemaVersionError",
    "ServiceStatus",
    "SourceStatus",
    "SourceView",
    "check_schema_version",
    "check_size",
    "peek_fields",
    "schema_major",
)

ENCODINGS: dict[str, str] = {
    "AnchorHistoryEntry": "3928c927d537545c",  # issue 46: forced, activated_by, how
    "AnchorHistoryReply": "99dee01ddba44a00",  # issue 46: its entries
    "AnchorPoint": "0f78399d8b04f214",
    "AnchorSetRejection": "292241e3265f60ae",  # issue 46: lost_to
    "AnchorSetReply": "d0867a9c7df48d2b",  # issue 46: accepted_at
    "CameraParked": "d1fabadf3045bcfc",  # 1.5 (issue 47)
    "CameraPlacement": "5cc07b0917eecea2",
    "CompactMapsMessage": "6dd57dc6be745b47",
    "ContextDistribution": "8d261f381245817e",
    "CreditGrant": "e358336bdce296a2",
    "ErrorReply": "6bb774f223f66240",
    "ExperienceStatus": "4af14e7641d86d54",
    "GridCameraStatus": "53933af7bcaf96a8",
    "GridHeader": "45032c519d91c5ab",
    "GridMessage": "d0c5c59150639ec0",  # 1.5: speed_png
    "GridStatus": "764176441651b45f",  # 1.5: speed_ago_s, speed_safe
    "ImageEnvelope": "afa63bf98b189131",
    "MapsHeader": "b69d7e8326586de9",
    "MapsMessage": "0b57008939444eab",
    "Message": "76091fdd70817734",
    "PathReply": "bb1eedee3874093d",
    "Pose2D": "8d8c2f26050aa8d8",
    "QuestionStatus": "34c954ab9f7e0fcd",
    "RelayHealth": "a13dd987488e86de",  # 1.6: safe_mask (issue 55)
    "ServiceStatus": "4fe3a85238c98fd0",  # 1.5: its GridStatus; store (issue 46)
    "SourceStatus": "b8cb4513be01ecb6",
    "SourceView": "d16a2d24f70c230c",
}


def wire_shapes() -> dict[str, type[WireModel]]:
    """Every wire model the messages package exports, by name."""
    return {
        name: value
        for name in NAMES
        if inspect.isclass(value := getattr(messages, name)) and issubclass(value, WireModel)
    }


def filled(annotation: Any, metadata: list[Any] | None = None) -> Any:
    """A value of ``annotation`` with every optional part present (the first member of a union that is not None)."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is typing.Annotated:
        return filled(args[0], list(args[1:]))
    if origin in (typing.Union, types.UnionType):
        return filled(next(arg for arg in args if arg is not type(None)))
    if origin is tuple:
        return tuple(filled(arg) for arg in args)
    if origin is list:
        return [filled(args[0])]
    if origin is dict:
        return {"key": filled(args[1])}
    if inspect.isclass(annotation) and issubclass(annotation, Enum):
        return next(iter(annotation))
    if annotation is AnchorSet:
        return default_anchor_set()
    if inspect.isclass(annotation) and issubclass(annotation, BaseModel):
        return instance_of(annotation)
    lowest = max((m.ge for m in metadata or [] if isinstance(m, annotated_types.Ge)), default=0)
    values: dict[Any, Any] = {float: 1.5, int: 2 + lowest, str: "s", bytes: b"b", bool: True}
    return values[annotation]


def instance_of(model: type[BaseModel]) -> BaseModel:
    values = {name: filled(field.annotation, field.metadata) for name, field in model.model_fields.items()}
    if "schema_version" in values:
        values["schema_version"] = "1.0"
    return model(**values)


def encoding_hash(model: type[BaseModel]) -> str:
    data = instance_of(model).model_dump(mode="python")
    return hashlib.sha256(msgpack.packb(data, use_bin_type=True)).hexdigest()[:16]


def test_every_name_of_the_single_module_still_imports() -> None:
    missing = [name for name in NAMES if not hasattr(messages, name)]
    assert missing == []


def test_every_wire_shape_encodes_as_before() -> None:
    shapes = wire_shapes()
    assert len(shapes) >= 25
    assert {name: encoding_hash(model) for name, model in shapes.items()} == ENCODINGS


def test_the_filler_sets_every_optional_field() -> None:
    """A shape's hash covers its optional fields only if the filler sets them: a None would hide a change of
    the field's type."""
    header = instance_of(messages.GridHeader)
    assert header.capture_pose is not None and header.robot is not None and header.age_s is not None


if __name__ == "__main__":
    print("ENCODINGS: dict[str, str] = {")
    for name, model in wire_shapes().items():
        print(f'    "{name}": "{encoding_hash(model)}",')
    print("}")
