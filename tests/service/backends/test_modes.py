"""The one table of runtime modes: it agrees with the settings' literal, and callers read it."""

from __future__ import annotations

import pytest
from gcdtrav.schemas.settings import PRECISIONS, ServiceSettings
from gcdtrav.service.backends import modes
from gcdtrav.service.backends.modes import MODES, NAMES, missing_requirement, modes_with, runtime_mode


def test_the_table_and_the_settings_literal_list_the_same_modes_in_the_same_order() -> None:
    assert NAMES == PRECISIONS
    assert len({m.name for m in MODES}) == len(MODES)
    for name in NAMES:
        ServiceSettings(precision=name)  # every name of the table is a valid setting


def test_every_mode_is_described_completely() -> None:
    for mode in MODES:
        assert mode.runtime in ("torch", "onnxruntime") and mode.trunk in ("fp32", "bf16", "int8")
        assert mode.decoder in ("fp32", "bf16", "int8") and mode.description
        assert mode.on_onnxruntime == ("onnxruntime" in mode.needs)  # an ONNX Runtime mode needs it installed
        assert ("native-bf16" in mode.needs) == ("bf16" in (mode.trunk, mode.decoder))


def test_runtime_mode_refuses_auto_and_unknown_names() -> None:
    assert runtime_mode("ort-int8").decoder == "int8"
    for name in ("auto", "fp8", ""):
        with pytest.raises(ValueError, match="precision must be one of auto, fp32"):
            runtime_mode(name)


@pytest.mark.parametrize(
    ("has", "expected"),
    [
        (set(), ["fp32", "int8"]),
        ({"onnxruntime"}, ["fp32", "int8", "ort-fp32", "ort-int8-vit", "ort-int8"]),
        ({"native-bf16"}, ["fp32", "bf16", "bf16-vit", "int8"]),
        ({"native-bf16", "onnxruntime"}, [m.name for m in MODES]),
    ],
)
def test_the_modes_a_machine_runs_follow_its_features(has: set[str], expected: list[str]) -> None:
    assert modes_with(lambda need: need in has) == expected


def test_only_onnxruntime_is_a_hard_requirement() -> None:
    """bf16 runs anywhere (emulated and slow, so auto leaves it out); an ort-* mode cannot be built without it."""
    nothing = lambda need: False  # noqa: E731
    assert missing_requirement(runtime_mode("bf16"), nothing) is None
    assert missing_requirement(runtime_mode("ort-fp32"), nothing) == "onnxruntime"
    assert set(modes.REQUIRED) == {"onnxruntime"}


def test_check_precision_says_what_is_missing(monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("torch")
    from gcdtrav.service.backends import clipseg
    from gcdtrav.service.backends.base import ModelUnavailableError

    monkeypatch.setattr(clipseg, "machine_has", lambda need: need != "onnxruntime")
    with pytest.raises(ModelUnavailableError, match="needs ONNX Runtime"):
        clipseg.check_precision("ort-int8-vit")
    assert clipseg.check_precision("bf16") == "bf16"
