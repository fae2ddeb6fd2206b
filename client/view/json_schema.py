"""JSON schemas that Foxglove-family viewers can parse, from pydantic models.

pydantic writes ``$ref``/``$defs``, ``anyOf [X, null]`` for optional fields and ``prefixItems`` for tuples.
Lichtblick's parser (packages/mcap-support/src/parseJsonSchema.ts) reads none of these and rejects the whole
channel ("Failed to parse channel schema"). ``flat_schema`` rewrites a model's schema to the plain subset it
reads: every node has a ``type``; objects have ``properties``, arrays ``items``; ``description`` and
``enum`` are kept, everything else (defaults, titles, bounds, ``additionalProperties``) is dropped.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel

KEPT = ("type", "description", "enum")
NUMERIC = {"integer", "number"}

Schema = dict[str, Any]


class UnflattenableSchema(ValueError):
    """A schema construct with no plain equivalent (a union of different types, a bare ``Any``)."""


def model_schema(model: type[BaseModel], title: str) -> Schema:
    """``model``'s JSON schema, flat, named ``title`` (foxglove-sdk takes the schema name from it)."""
    return {"title": title, **flat_schema(model.model_json_schema())}


def flat_schema(schema: Schema) -> Schema:
    """``schema`` with every ``$ref`` inlined, optionals as their type and tuples as arrays (see module doc)."""
    return _flat(schema, schema.get("$defs", {}), path="", seen=())


def _flat(node: Schema, definitions: Schema, path: str, seen: tuple[str, ...]) -> Schema:
    node, seen = _resolved(node, definitions, path, seen)
    node = _without_null(node, definitions, path, seen)
    flat: Schema = {key: node[key] for key in KEPT if key in node}
    if "type" not in flat:
        flat["type"] = _type_of(node, path)
    if flat["type"] == "object":
        properties = node.get("properties", {})
        flat["properties"] = {name: _flat(sub, definitions, f"{path}.{name}", seen) for name, sub in properties.items()}
    elif flat["type"] == "array":
        flat["items"] = _items(node, definitions, path, seen)
    return flat


def _resolved(node: Schema, definitions: Schema, path: str, seen: tuple[str, ...]) -> tuple[Schema, tuple[str, ...]]:
    """The node a ``$ref`` points to, with the referring node's description (it says what this field is)."""
    reference = node.get("$ref")
    if reference is None:
        return node, seen
    name = reference.removeprefix("#/$defs/")
    if name in seen:
        raise UnflattenableSchema(f"{path or 'root'}: {name} refers to itself; a flat schema cannot hold it")
    if name not in definitions:
        raise UnflattenableSchema(f"{path or 'root'}: unknown reference {reference}")
    target = dict(definitions[name])
    if "description" in node:
        target["description"] = node["description"]
    return target, (*seen, name)


def _without_null(node: Schema, definitions: Schema, path: str, seen: tuple[str, ...]) -> Schema:
    """``anyOf [X, null]`` (an optional field) becomes X; the field may still hold null."""
    alternatives = node.get("anyOf") or node.get("oneOf")
    if not alternatives:
        return node
    kept = [alternative for alternative in alternatives if alternative.get("type") != "null"]
    if len(kept) != 1:
        raise UnflattenableSchema(f"{path or 'root'}: a union of {len(kept)} types has no single type")
    chosen, _ = _resolved(kept[0], definitions, path, seen)
    merged = {key: value for key, value in node.items() if key not in ("anyOf", "oneOf")}
    return {**chosen, **{key: merged[key] for key in KEPT if key in merged}}


def _type_of(node: Schema, path: str) -> str:
    kind = node.get("type")
    if isinstance(kind, list):  # ["string", "null"]
        kinds = [k for k in kind if k != "null"]
        if len(kinds) == 1:
            return str(kinds[0])
    if "enum" in node and all(isinstance(v, str) for v in node["enum"]):
        return "string"
    raise UnflattenableSchema(f"{path or 'root'}: no single type in {sorted(node)}")


def _items(node: Schema, definitions: Schema, path: str, seen: tuple[str, ...]) -> Schema:
    """An array's item schema; a tuple's (``prefixItems``) is its members' common type."""
    if "items" in node:
        return _flat(node["items"], definitions, f"{path}[]", seen)
    members = [_flat(member, definitions, f"{path}[]", seen) for member in node.get("prefixItems", [])]
    kinds = {member["type"] for member in members}
    if members and all(member == members[0] for member in members):
        return members[0]
    if len(kinds) == 1 and not kinds & {"object", "array"}:
        return {"type": kinds.pop()}
    if kinds and kinds <= NUMERIC:
        return {"type": "number"}
    raise UnflattenableSchema(f"{path or 'root'}: tuple members {sorted(kinds)} have no common type")
