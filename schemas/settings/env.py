"""Settings from a YAML file, ``GCDTRAV_*`` environment variables and command-line overrides, in that order."""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from gcdtrav.schemas.settings.base import ENV_PREFIX, SettingsError
from gcdtrav.schemas.settings.service import ServiceSettings
from gcdtrav.schemas.settings.store import PASSWORD_ENV
from gcdtrav.schemas.strict import problems
from gcdtrav.schemas.yaml_file import load_mapping
from pydantic import BaseModel, ValidationError

log = logging.getLogger("gcdtrav.settings")
NOT_SETTINGS = frozenset({PASSWORD_ENV})  # GCDTRAV_* variables read elsewhere: a secret is never a setting


def unknown_setting(path: list[str], section: type[BaseModel] | None = None) -> str | None:
    """None if ``path`` (lower-case names, nested) names a setting; else the names that exist where it strays."""
    model: type[BaseModel] = section or ServiceSettings
    for depth, part in enumerate(path):
        field = model.model_fields.get(part)
        if field is None:
            return ", ".join(ENV_PREFIX + "__".join([*path[:depth], name]).upper() for name in model.model_fields)
        nested = field.annotation
        if depth + 1 < len(path):
            if not (isinstance(nested, type) and issubclass(nested, BaseModel)):
                return f"{ENV_PREFIX}{'__'.join(path[: depth + 1]).upper()} (a value, not a section)"
            model = nested
    return None


def _env_overrides(environ: Mapping[str, str]) -> dict[str, Any]:
    """GCDTRAV_HISTORY=4, GCDTRAV_INPUTS='["a/**","b/*"]' or 'a/**,b/*', GCDTRAV_ENGINE__METHOD=argmax.
    A GCDTRAV_* variable that names no setting is ignored with a warning (a stray variable in a user's shell
    must not stop the service); one that names a setting is checked like any other source of it."""
    result: dict[str, Any] = {}
    for name, raw in environ.items():
        if not name.startswith(ENV_PREFIX) or name in NOT_SETTINGS:
            continue
        path = name[len(ENV_PREFIX) :].lower().split("__")
        if (settings := unknown_setting(path)) is not None:
            log.warning("environment variable %s is not a setting and is ignored; the settings: %s", name, settings)
            continue
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
        where = f"{file}: " if file else ""
        raise SettingsError(where + "invalid settings: " + problems(err)) from None
