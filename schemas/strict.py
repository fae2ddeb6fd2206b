"""The two bases of every shape in ``schemas``, and the rule that picks one (docs/messages.md, "Compatibility").

- **Configuration** (anchor sets, settings) is strict: an unknown field is an error, never ignored. A
  misspelt setting (``histroy_depth: 8``) must fail loudly where it enters, as Frigate's
  ``FrigateBaseModel`` does for its config tree.
- **Wire messages** (what crosses the bus between services, robots, planners and operators) ignore fields
  they do not know: robots, planners and services upgrade one at a time, and a field a newer peer adds must
  not break an older reader. Unknown fields are dropped, never kept in the model. What a reader cannot
  survive is a new *major* schema version, checked in ``messages.Message.validated``.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, ValidationError


class StrictModel(BaseModel):
    """Configuration: unknown fields are an error."""

    model_config = ConfigDict(extra="forbid")


class FrozenStrictModel(BaseModel):
    """Strict and immutable: values that are hashed or shared (anchor sets, engine settings)."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class WireModel(BaseModel):
    """A message or a part of one on the bus: fields a newer sender added are ignored (and not kept)."""

    model_config = ConfigDict(extra="ignore")


def problems(err: ValidationError, most: int | None = None) -> str:
    """A validation error on one line: each field and what is wrong with it (the first ``most`` of them)."""
    return "; ".join(
        f"{'.'.join(map(str, e['loc']))}: {e['msg']}" if e["loc"] else e["msg"] for e in err.errors()[:most]
    )
