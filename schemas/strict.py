"""The one base of every message and configuration shape: unknown fields are an error, never ignored.

A misspelt setting (``histroy_depth: 8``) or a field from a newer client must fail loudly where it
enters, as Frigate's ``FrigateBaseModel`` does for its config tree.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class StrictModel(BaseModel):
    model_config = ConfigDict(extra="forbid")


class FrozenStrictModel(BaseModel):
    """Strict and immutable: values that are hashed or shared (anchor sets, engine settings)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
