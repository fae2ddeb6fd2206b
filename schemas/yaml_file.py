"""A settings file: a YAML mapping, or a clear error naming the file (the strict models check its fields)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml


def load_mapping(file: str | Path, what: str, error: type[ValueError]) -> dict[str, Any]:
    """The file's mapping ({} for an empty file); ``error`` naming the file if it is unreadable or not a mapping."""
    try:
        loaded = yaml.safe_load(Path(file).read_text("utf-8")) or {}
    except (OSError, yaml.YAMLError) as err:
        raise error(f"{file}: cannot read the {what}: {err}") from None
    if not isinstance(loaded, dict):
        raise error(f"{file}: expected a mapping of settings")
    return loaded
