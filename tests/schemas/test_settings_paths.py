"""State and cache directories follow XDG and are always expanded: no folder literally named '~'."""

from __future__ import annotations

from pathlib import Path

import pytest
from gcdtrav.schemas.paths import default_cache_dir, default_state_dir
from gcdtrav.schemas.settings import ServiceSettings, load_settings


@pytest.fixture()
def home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.delenv("XDG_STATE_HOME", raising=False)
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    return tmp_path


def test_without_xdg_variables_the_defaults_are_under_home(home: Path) -> None:
    settings = ServiceSettings()
    assert settings.state_dir == home / ".local" / "state" / "gcdtrav"
    assert settings.cache_dir == home / ".cache" / "gcdtrav"
    assert settings.state_file.parent == settings.state_dir and "~" not in str(settings.state_file)


def test_xdg_variables_win(home: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XDG_STATE_HOME", str(home / "state"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(home / "cache"))
    settings = ServiceSettings()
    assert (settings.state_dir, settings.cache_dir) == (home / "state" / "gcdtrav", home / "cache" / "gcdtrav")


def test_a_relative_xdg_value_is_ignored_as_the_specification_asks(home: Path) -> None:
    environ = {"XDG_STATE_HOME": "relative/state", "XDG_CACHE_HOME": ""}
    assert default_state_dir(environ) == home / ".local" / "state" / "gcdtrav"
    assert default_cache_dir(environ) == home / ".cache" / "gcdtrav"


def test_a_user_given_tilde_is_expanded_from_every_source(home: Path, tmp_path: Path) -> None:
    assert ServiceSettings(state_dir=Path("~/s"), cache_dir=Path("~/c")).state_dir == home / "s"
    assert ServiceSettings(cache_dir="~/c").cache_dir == home / "c"  # type: ignore[arg-type]
    from_env = load_settings(environ={"GCDTRAV_STATE_DIR": "~/env-state", "GCDTRAV_CACHE_DIR": "~/env-cache"})
    assert (from_env.state_dir, from_env.cache_dir) == (home / "env-state", home / "env-cache")
    file = tmp_path / "settings.yaml"
    file.write_text("state_dir: ~/file-state\n")
    assert load_settings(file, {"cache_dir": "~/flag-cache"}, environ={}).cache_dir == home / "flag-cache"
    assert load_settings(file, environ={}).state_dir == home / "file-state"
