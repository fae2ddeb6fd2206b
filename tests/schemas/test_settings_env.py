"""GCDTRAV_* variables: settings are read, a stray variable in a user's shell is named and ignored."""

from __future__ import annotations

import logging

import pytest
from gcdtrav.schemas.settings import SettingsError, load_settings


def test_a_variable_that_is_not_a_setting_is_warned_once_and_ignored(caplog: pytest.LogCaptureFixture) -> None:
    environ = {
        "GCDTRAV_WEIGHTS": "~/clipseg",  # deploy/compose.yaml's, on the host
        "GCDTRAV_HISTORY": "4",
        "GCDTRAV_ENGINE__METHOD": "argmax",
        "GCDTRAV_ENGINE__NOPE": "1",
        "GCDTRAV_HISTORY__DEPTH": "2",
        "GCDTRAV_CLOCK": "synced",
        "PATH": "/bin",
    }
    with caplog.at_level(logging.WARNING, "gcdtrav.settings"):
        settings = load_settings(environ=environ)
    assert settings.history == 4 and settings.engine.method.value == "argmax" and settings.clock == "synced"
    warned = {r.getMessage().split()[2]: r.getMessage() for r in caplog.records}
    assert set(warned) == {"GCDTRAV_WEIGHTS", "GCDTRAV_ENGINE__NOPE", "GCDTRAV_HISTORY__DEPTH"}
    assert "GCDTRAV_MAX_FRAME_AGE_S" in warned["GCDTRAV_WEIGHTS"] and "GCDTRAV_CLOCK" in warned["GCDTRAV_WEIGHTS"]
    assert "GCDTRAV_ENGINE__METHOD" in warned["GCDTRAV_ENGINE__NOPE"]
    assert "a value, not a section" in warned["GCDTRAV_HISTORY__DEPTH"]


def test_a_setting_with_a_bad_value_still_refuses_to_start() -> None:
    with pytest.raises(SettingsError, match="clock"):
        load_settings(environ={"GCDTRAV_CLOCK": "ntp"})
    with pytest.raises(SettingsError, match="intake_rate_per_publisher"):
        load_settings(environ={"GCDTRAV_INTAKE_RATE_PER_PUBLISHER": "0"})
