"""Every JSON channel `gcdtrav view` advertises has a schema Lichtblick can parse.

``lichtblick_datatypes`` is a Python port of what Lichtblick's JSON-schema parser accepts and rejects, read in
lichtblick-suite/lichtblick at commit 66adecb99ca4363b1028c750919c9046609f5c85 (2026-08-07),
packages/mcap-support/src/parseJsonSchema.ts (parseChannel.ts hands it every "json" channel with a
"jsonschema" schema). A parse error there is the "Failed to parse channel schema" alert, and the channel
is dropped.
"""

from __future__ import annotations

import asyncio
import base64
import json
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("foxglove", reason="the view extra: pip install 'gcdtrav[view]'")
pytest.importorskip("websockets")

from foxglove_ws import FoxgloveClient
from gcdtrav.client.view.json_schema import UnflattenableSchema, flat_schema, model_schema
from gcdtrav.client.view.viewer import ServiceStatuses, Viewer, ViewOptions
from gcdtrav.schemas.messages import AnchorSetReply, SourceView
from pydantic import BaseModel
from view_fakes import FakeClient, maps_payload

MODELS = ((AnchorSetReply, "gcdtrav.AnchorSetReply"), (ServiceStatuses, "gcdtrav.ServiceStatuses"),
          (SourceView, "gcdtrav.SourceView"))  # fmt: skip
JSON_TOPICS = ("/gcdtrav/anchors", "/gcdtrav/status", "/gcdtrav/cam/status")


class LichtblickRejects(ValueError):
    pass


Datatypes = dict[str, list[tuple[str, str, bool]]]  # type name -> (field, type, is array)


def lichtblick_datatypes(schema: dict[str, Any], type_name: str) -> Datatypes:
    """Port of parseJsonSchema's addFieldsRecursive: the datatypes Lichtblick makes of ``schema``, or the
    error it throws. Like the original, anything not listed here is ignored ($defs, required, titles ...)."""
    datatypes: Datatypes = {}
    _add_fields(schema, type_name, [], datatypes)
    return datatypes


def _add_fields(schema: dict[str, Any], type_name: str, key_path: list[str], datatypes: Datatypes) -> None:
    if schema.get("type") != "object":
        raise LichtblickRejects(f'Expected "type": "object" for schema {type_name}, got {schema.get("type")!r}')
    fields: list[tuple[str, str, bool]] = []
    for name, field in (schema.get("properties") or {}).items():
        where = ".".join([*key_path, name])
        if isinstance(field.get("oneOf"), list):
            if not all(isinstance(alternative.get("const"), int | float) for alternative in field["oneOf"]):
                raise LichtblickRejects(f"Unsupported type for {where}: oneOf alternatives must have number values")
            fields.append((name, "uint32", False))
            continue
        kind = field.get("type")
        if kind in ("boolean", "number", "integer"):
            fields.append((name, kind, False))
        elif kind == "string":
            if field.get("contentEncoding") not in (None, "base64"):
                raise LichtblickRejects(f"Unsupported contentEncoding {field['contentEncoding']!r} in {where}")
            fields.append((name, "string", False))
        elif kind == "object":
            _add_fields(field, f"{type_name}.{name}", [*key_path, name], datatypes)
            fields.append((name, f"{type_name}.{name}", False))
        elif kind == "array":
            fields.append(_array_field(field, name, type_name, [*key_path, name], datatypes))
        else:  # "null", a list of types, none (a bare $ref or anyOf)
            raise LichtblickRejects(f"Unsupported type {kind!r} for {where}")
    datatypes[type_name] = fields


def _array_field(
    field: dict[str, Any], name: str, type_name: str, key_path: list[str], datatypes: Datatypes
) -> tuple[str, str, bool]:
    items = field.get("items")
    if not isinstance(items, dict):  # TypeError reading items.type in the original
        raise LichtblickRejects(f"Cannot read properties of {items!r} (reading 'type') for {'.'.join(key_path)}")
    kind = items.get("type")
    if kind in ("boolean", "number", "integer"):
        return name, kind, True
    if kind == "string" and items.get("contentEncoding") is None:
        return name, "string", True
    if kind == "object":
        _add_fields(items, f"{type_name}.{name}", key_path, datatypes)
        return name, f"{type_name}.{name}", True
    raise LichtblickRejects(f"Unsupported type {kind!r} for array item {'.'.join(key_path)}")


def test_the_port_rejects_what_lichtblick_rejects() -> None:
    def rejected(properties: dict[str, Any]) -> bool:
        try:
            lichtblick_datatypes({"type": "object", "properties": properties}, "T")
        except LichtblickRejects:
            return True
        return False

    assert rejected({"a": {"$ref": "#/$defs/A"}})
    assert rejected({"a": {"anyOf": [{"type": "integer"}, {"type": "null"}]}})
    assert rejected({"a": {"type": "array", "prefixItems": [{"type": "integer"}]}})
    assert rejected({"a": {"type": "array", "items": {"type": "array", "items": {"type": "number"}}}})
    assert rejected({"a": {"type": ["string", "null"]}}) and rejected({"a": {"type": "null"}})
    assert rejected({"a": {"oneOf": [{"const": "x"}]}})
    assert not rejected({"a": {"type": "string", "enum": ["x"]}, "b": {"type": "object"}})
    assert not rejected({"a": {"type": "array", "items": {"type": "object", "properties": {"b": {"type": "integer"}}}}})


@pytest.mark.parametrize(("model", "title"), MODELS)
def test_pydantic_schemas_fail_and_flat_ones_pass(model: type[BaseModel], title: str) -> None:
    with pytest.raises(LichtblickRejects):
        lichtblick_datatypes(model.model_json_schema(), title)
    flat = model_schema(model, title)
    assert flat["title"] == title and "$defs" not in json.dumps(flat) and "$ref" not in json.dumps(flat)
    lichtblick_datatypes(flat, title)


def test_flat_schemas_keep_fields_types_and_descriptions() -> None:
    flat = model_schema(SourceView, "gcdtrav.SourceView")
    datatypes = lichtblick_datatypes(flat, "gcdtrav.SourceView")
    header = dict((name, (kind, is_array)) for name, kind, is_array in datatypes["gcdtrav.SourceView.maps"])
    assert header["image_size"] == ("integer", True) and header["scale"] == ("number", True)
    assert header["method"] == ("string", False) and header["seq"] == ("integer", False)
    maps = flat["properties"]["maps"]
    assert maps["description"] == "Header of the latest maps received."  # the field's, not its model's
    assert maps["properties"]["method"]["enum"] == ["gcd", "argmax", "gaussian"]
    anchors = lichtblick_datatypes(model_schema(AnchorSetReply, "A"), "A")["A.anchor_set.anchors"]
    assert ("width", "number", False) in anchors  # optional float -> number


def test_unions_and_mixed_tuples_are_refused_not_guessed() -> None:
    two_types = {"type": "object", "properties": {"a": {"anyOf": [{"type": "integer"}, {"type": "string"}]}}}
    with pytest.raises(UnflattenableSchema, match=r"\.a: a union of 2 types"):
        flat_schema(two_types)
    mixed = {"type": "object", "properties": {"t": {"type": "array", "prefixItems": [{"type": "string"},
                                                                                    {"type": "number"}]}}}  # fmt: skip
    with pytest.raises(UnflattenableSchema, match="no common type"):
        flat_schema(mixed)
    numbers = {"type": "array", "prefixItems": [{"type": "integer"}, {"type": "number"}]}
    assert flat_schema({"type": "object", "properties": {"t": numbers}})["properties"]["t"]["items"] == {
        "type": "number"
    }


async def advertised_json_schemas(url: str) -> dict[str, tuple[str, dict[str, Any]]]:
    fox = await FoxgloveClient.connect(url)
    await fox.until(lambda: all(topic in fox.channels for topic in JSON_TOPICS))
    await fox.close()
    return {
        topic: (channel["schemaName"], json.loads(channel["schema"]))
        for topic, channel in fox.channels.items()
        if channel["encoding"] == "json"
    }


def test_every_json_channel_the_viewer_advertises_parses_in_lichtblick() -> None:
    client = FakeClient()
    with Viewer(client, ViewOptions(port=0)) as viewer:
        client.session.put("gcdtrav/out/cam/maps", maps_payload("cam", (4, 4), (8, 8)))
        advertised = asyncio.run(advertised_json_schemas(viewer.url))
    assert set(advertised) == set(JSON_TOPICS)
    for topic, (name, schema) in advertised.items():
        lichtblick_datatypes(schema, name)  # raises LichtblickRejects naming the field
        print(topic, name, "ok")


async def every_channel(url: str) -> dict[str, dict[str, Any]]:
    fox = await FoxgloveClient.connect(url)
    await fox.until(lambda: "/gcdtrav/cam/question" in fox.channels and "/gcdtrav/cam/grid/costmap" in fox.channels)
    await fox.close()
    return fox.channels


def test_every_channel_of_a_source_with_everything_has_a_schema_lichtblick_reads(tmp_path: Path) -> None:
    """JSON channels through the port of Lichtblick's parser; protobuf channels' schemas are FileDescriptorSets
    holding the message they name (what Lichtblick hands protobufjs)."""
    pytest.importorskip("google.protobuf")
    pytest.importorskip("rosbags")
    import msgpack
    from google.protobuf import descriptor_pb2, descriptor_pool
    from test_view_operator import SETTINGS, feed

    settings = tmp_path / "gcdtrav.yaml"
    settings.write_text(SETTINGS)
    client = FakeClient()
    with Viewer(client, ViewOptions(port=0, settings=settings)) as viewer:  # type: ignore[arg-type]
        feed(viewer, client)
        client.session.put("gcdtrav/out/cam/question", msgpack.packb({"id": "q", "text": "mud?"}))
        viewer.set_probe({"probe/source": "cam"})
        channels = asyncio.run(every_channel(viewer.url))
    new = {"grid/cvar", "grid/p_below", "grid/match", "grid/costmap", "grid/cvar/image", "tf", "robot",
           "camera_info", "distribution", "question"}  # fmt: skip
    assert {f"/gcdtrav/cam/{name}" for name in new} <= set(channels)
    for topic, channel in channels.items():
        if channel["encoding"] == "json":
            lichtblick_datatypes(json.loads(channel["schema"]), channel["schemaName"])
            continue
        assert (channel["encoding"], channel["schemaEncoding"]) == ("protobuf", "protobuf"), topic
        files = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
        pool = descriptor_pool.DescriptorPool()
        for file in files.file:
            pool.Add(file)
        assert pool.FindMessageTypeByName(channel["schemaName"]).full_name == channel["schemaName"], topic
