"""Where gcdtrav keeps files between runs, following the XDG base directories, always expanded.

state (the last accepted anchor set): ``$XDG_STATE_HOME/gcdtrav``, else ``~/.local/state/gcdtrav``;
cache (ONNX exports, the measurement of ``precision: auto``): ``$XDG_CACHE_HOME/gcdtrav``, else
``~/.cache/gcdtrav``. A relative ``XDG_*`` value is ignored, as the specification asks. Nothing is ever
written to a folder literally named ``~``: every path a user gives is expanded too.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

APP = "gcdtrav"


def _xdg_home(variable: str, fallback: str, environ: Mapping[str, str] | None) -> Path:
    value = (os.environ if environ is None else environ).get(variable, "")
    base = Path(value) if value and Path(value).is_absolute() else Path.home() / fallback
    return base / APP


def default_state_dir(environ: Mapping[str, str] | None = None) -> Path:
    return _xdg_home("XDG_STATE_HOME", ".local/state", environ)


def default_cache_dir(environ: Mapping[str, str] | None = None) -> Path:
    return _xdg_home("XDG_CACHE_HOME", ".cache", environ)


def expanded(path: str | Path) -> Path:
    """``~`` and ``~user`` expanded; anything else as given."""
    return Path(path).expanduser()
