"""The active anchor set as Foxglove parameters, and edits of them turned into a whole new set.

Parameters (a flat name -> value map, so Foxglove's Parameters panel edits each field):

    anchors/name            str     the set's label
    anchors/default_width   float   sigma of anchors without their own width
    anchors/NN/concept      str     anchor NN's text prompt (NN = 00, 01, ... in position order)
    anchors/NN/position     float   its place on the traversability scale [0, 1]
    anchors/NN/width        float   its own width, or null (None) where it follows default_width; null sets it back
    anchors/json            str     the whole set as JSON: paste a set here to add or remove anchors

An edit is applied to a copy of the active set and the result validated as a whole with the same pydantic
model the service uses, so a set is swapped entirely or not at all. Problems name the parameters.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

from gcdtrav.schemas.anchors import AnchorSet, AnchorSetError

PREFIX = "anchors"
JSON_PARAMETER = f"{PREFIX}/json"
SET_FIELDS = {"name": str, "default_width": float}
ANCHOR_FIELDS = {"concept": str, "position": float, "width": float}
_ANCHOR_NAME = re.compile(rf"^{PREFIX}/(\d+)/(\w+)$")
_MESSAGE_FIELD = re.compile(r"^anchors\.(\d+)\.(\w+)")

ParameterValue = str | float | None


def anchor_parameter(index: int, field: str) -> str:
    return f"{PREFIX}/{index:02d}/{field}"


def anchor_parameters(anchors: AnchorSet) -> dict[str, ParameterValue]:
    """Every parameter of ``anchors``, in the order the Parameters panel lists them."""
    values: dict[str, ParameterValue] = {f"{PREFIX}/name": anchors.name}
    values[f"{PREFIX}/default_width"] = anchors.default_width
    for index, anchor in enumerate(anchors.anchors):
        values[anchor_parameter(index, "concept")] = anchor.concept
        values[anchor_parameter(index, "position")] = anchor.position
        values[anchor_parameter(index, "width")] = anchor.width  # null as the set says: it follows default_width
    values[JSON_PARAMETER] = anchors.model_dump_json(exclude_none=True)
    return values


def apply_parameters(active: AnchorSet, changes: Mapping[str, object]) -> AnchorSet:
    """The set ``active`` becomes with ``changes`` (parameter name -> new value), validated as a whole.

    Raises AnchorSetError whose messages start with the parameter they concern.
    """
    if JSON_PARAMETER in changes:
        if len(changes) > 1:
            others = ", ".join(sorted(set(changes) - {JSON_PARAMETER}))
            raise AnchorSetError([f"{JSON_PARAMETER} replaces the whole set: set it alone, not with {others}"])
        text = changes[JSON_PARAMETER]
        if not isinstance(text, str):
            raise AnchorSetError([f"{JSON_PARAMETER}: expected the set as JSON text, got {type(text).__name__}"])
        try:
            return AnchorSet.from_text(text)
        except AnchorSetError as err:
            raise AnchorSetError([f"{JSON_PARAMETER}: {message}" for message in err.messages]) from None
    document: dict[str, Any] = active.model_dump()
    problems: list[str] = []
    for name, value in changes.items():
        problem = _apply(document, active, name, value)
        if problem:
            problems.append(f"{name}: {problem}")
    if problems:
        raise AnchorSetError(problems)
    try:
        return AnchorSet.parse(document)
    except AnchorSetError as err:
        raise AnchorSetError([parameter_message(message, list(changes)) for message in err.messages]) from None


def _apply(document: dict[str, Any], active: AnchorSet, name: str, value: object) -> str | None:
    """Set one parameter in ``document``; a problem in words, or None."""
    field, target = name.removeprefix(f"{PREFIX}/"), document
    match = _ANCHOR_NAME.match(name)
    if match:
        index, field = int(match[1]), match[2]
        if index >= len(active) or field not in ANCHOR_FIELDS:
            last = anchor_parameter(len(active) - 1, "width")
            return f"no such parameter; the set has {anchor_parameter(0, 'concept')} .. {last}"
        kind, target = ANCHOR_FIELDS[field], document["anchors"][index]
        if field == "width" and value is None:
            target[field] = None  # follow default_width again
            return None
    elif name.startswith(f"{PREFIX}/") and field in SET_FIELDS:
        kind = SET_FIELDS[field]
    else:
        return f"no such parameter; the anchor set's parameters start with '{PREFIX}/'"
    converted = _typed(value, kind)
    if converted is None:
        return f"expected {'a number' if kind is float else 'text'}, got {value!r}"
    target[field] = converted
    return None


def _typed(value: object, kind: type) -> ParameterValue | None:
    if kind is float:
        is_number = isinstance(value, int | float) and not isinstance(value, bool)
        return float(value) if is_number else None  # type: ignore[arg-type]
    return value if isinstance(value, str) else None


def parameter_message(message: str, changed: list[str]) -> str:
    """A validation message of the anchor-set model, starting with the parameter it concerns: the field's
    parameter, or for a problem of the whole set (order, duplicates) the parameters just changed."""
    message = _MESSAGE_FIELD.sub(lambda m: anchor_parameter(int(m[1]), m[2]), message)
    if any(message.startswith(f"{field}:") for field in SET_FIELDS):
        return f"{PREFIX}/{message}"
    return message if message.startswith(f"{PREFIX}/") else f"{', '.join(changed)}: {message}"
