"""Settings from a YAML file, ``GCDTRAV_*`` environment variables and command-line overrides, in that order."""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from gcdtrav.schemas.settings.base import (
    ENV_PREFIX,
    SettingsError,
)
from gcdtrav.schemas.settings.service import ServiceSettings
from gcdtrav.schemas.yaml_file import load_mapping
from pydantic import ValidationError


def _env_overrides(environ: Mapping[str, str]) -> dict[str, Any]:
    """GCDTRAV_HISTORY=4, GCDTRAV_INPUTS='["a/**","b/*"]' or 'a/**,b/*', GCDTRAV_ENGINE__METHOD=argmax."""
    result: dict[str, Any] = {}
    for name, raw in environ.items():
        if not name.startswith(ENV_PREFIX):
            continue
        path = name[len(ENV_PREFIX) :].lower().split("__")
        value: Any = raw
        if path == ["inputs"] and not raw.lstrip().startswith("["):
            value = [part.strip() for part in raw.split(",") if part.strip()]
        elif raw.lstrip().startswith(("[", "{")):
            value = json.loads(raw)
        target = result
        for part in path[:-1]:
            target = target.setdefault(part, {})
        target[path[-1]] = value
    return result


def _merge(base: dict[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    merged = dict(base)
    for key, value in override.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), dict):
            merged[key] = _merge(merged[key], value)
        else:
            merged[key] = value
    return merged


def load_settings(
    file: str | Path | None = None,
    overrides: Mapping[str, Any] | None = None,
    environ: Mapping[str, str] | None = None,
) -> ServiceSettings:
    data = load_mapping(file, "settings file", SettingsError) if file is not None else {}
    env = os.environ if environ is None else environ
    try:
        data = _merge(data, _env_overrides(env))
    except json.JSONDecodeError as err:
        raise SettingsError(f"a {ENV_PREFIX}* variable is not valid JSON: {err}") from None
    data = _merge(data, {k: v for k, v in (overrides or {}).items() if v is not None})
    try:
        return ServiceSettings.model_validate(data)
    except ValidationError as err:
        problems = [f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in err.errors()]
        where = f"{file}: " if file else ""
        raise SettingsError(where + "invalid settings: " + "; ".join(problems)) from None
