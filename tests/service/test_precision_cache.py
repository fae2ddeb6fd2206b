"""One cache of auto's measurement: doctor fills it, infer/serve read it; serve measures in the background and
switches between frames."""

from __future__ import annotations

import argparse
import json
import threading
from pathlib import Path

import numpy as np
import pytest
from conftest import textured_image

pytest.importorskip("torch")

from gcdtrav.service.backends import precision_choice
from gcdtrav.service.backends.clipseg import ClipSegBackend, TorchCompute
from gcdtrav.service.backends.precision_choice import ModeMeasurement
from gcdtrav.service.commands import doctor

CONCEPTS = ["water", "grass", "asphalt"]
# int8 wins on these figures; no machine's timing decides the test
FIGURES = [ModeMeasurement("fp32", 100.0, 0.0), ModeMeasurement("int8", 40.0, 0.001)]


def no_measuring(*args: object, **kwargs: object) -> list[ModeMeasurement]:
    raise AssertionError("measured again")


def test_doctor_fills_the_cache_that_infer_and_serve_read(
    tiny_model_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(precision_choice, "measure_modes", lambda *args, **kwargs: FIGURES)
    args = argparse.Namespace(model=str(tiny_model_dir), runs=1, cache_dir=tmp_path, measure=False)
    assert doctor.run(args) == doctor.EXIT_OK
    assert "precision auto picks int8 here" in capsys.readouterr().out
    assert len(list((tmp_path / "precision").glob("*.json"))) == 1

    monkeypatch.setattr(precision_choice, "measure_modes", no_measuring)
    for measure_now in (True, False):  # infer's way and serve's way
        backend = ClipSegBackend(str(tiny_model_dir), precision="auto", cache_dir=tmp_path, measure_now=measure_now)
        assert backend.precision == "int8" and backend.precision_reason.endswith(", cached)")
        assert not backend.needs_measurement
    assert doctor.run(args) == doctor.EXIT_OK  # a second doctor shows the cached figures
    out = capsys.readouterr().out
    assert "cached in" in out and "precision auto picks int8 here" in out


def test_doctor_measure_replaces_the_cached_figures(
    tiny_model_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(precision_choice, "measure_modes", lambda *args, **kwargs: FIGURES)
    args = argparse.Namespace(model=str(tiny_model_dir), runs=1, cache_dir=tmp_path, measure=False)
    doctor.run(args)
    slower_int8 = [FIGURES[0], ModeMeasurement("int8", 400.0, 0.001)]
    monkeypatch.setattr(precision_choice, "measure_modes", lambda *args, **kwargs: slower_int8)
    doctor.run(argparse.Namespace(**{**vars(args), "measure": True}))
    assert "precision auto picks fp32 here" in capsys.readouterr().out
    assert ClipSegBackend(str(tiny_model_dir), precision="auto", cache_dir=tmp_path).precision == "fp32"


def test_serve_way_runs_fp32_while_measuring_then_switches_between_frames(
    tiny_model_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    backend = ClipSegBackend(str(tiny_model_dir), precision="auto", cache_dir=tmp_path, measure_now=False)
    assert backend.precision == "fp32" and backend.needs_measurement and not backend.measuring
    assert "measuring in the background" in backend.precision_reason
    release, started = threading.Event(), threading.Event()

    def slow_measurement(*args: object, **kwargs: object) -> list[ModeMeasurement]:
        started.set()
        assert release.wait(60)
        return FIGURES

    monkeypatch.setattr(precision_choice, "measure_modes", slow_measurement)
    prepared = backend.prepare(CONCEPTS)
    image = textured_image(80, 80)
    fp32 = backend.logits(image, prepared)
    thread = precision_choice.measure_in_background(backend)
    assert backend.measuring  # at once, before the thread runs
    assert started.wait(30)
    assert backend.precision == "fp32" and np.array_equal(backend.logits(image, prepared), fp32)  # still serving
    release.set()
    thread.join(60)
    assert not backend.measuring and not backend.needs_measurement
    assert backend.precision == "int8" and "fastest within the parity gate" in backend.precision_reason
    assert isinstance(backend.compute, TorchCompute) and backend.compute.trunk.layers[0] is not None
    assert len(backend.model.clip.vision_model.encoder.layers) == 0  # int8 runs a copy: fp32 layers released
    int8 = backend.logits(image, prepared)
    assert not np.array_equal(int8, fp32) and np.corrcoef(int8.ravel(), fp32.ravel())[0, 1] > 0.99
    [stored] = (tmp_path / "precision").glob("*.json")
    assert [m["mode"] for m in json.loads(stored.read_text())["measurements"]] == ["fp32", "int8"]


def test_a_failed_background_measurement_keeps_fp32_and_says_why(
    tiny_model_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def broken(*args: object, **kwargs: object) -> list[ModeMeasurement]:
        raise RuntimeError("timer exploded")

    backend = ClipSegBackend(str(tiny_model_dir), precision="auto", cache_dir=tmp_path, measure_now=False)
    monkeypatch.setattr(precision_choice, "measure_modes", broken)
    precision_choice.measure_in_background(backend).join(60)
    assert backend.precision == "fp32" and not backend.measuring
    assert "the measurement failed (timer exploded)" in backend.precision_reason
    assert backend.logits(textured_image(64, 64), backend.prepare(CONCEPTS)).shape[0] == len(CONCEPTS)


def test_a_mode_asked_for_is_never_measured(
    tiny_model_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(precision_choice, "measure_modes", no_measuring)
    backend = ClipSegBackend(str(tiny_model_dir), precision="int8", cache_dir=tmp_path, measure_now=False)
    assert backend.precision == "int8" and backend.precision_reason == "asked for int8"
    assert not backend.needs_measurement and not (tmp_path / "precision").exists()


def test_a_cancelled_measurement_stops_before_the_next_mode_and_caches_nothing(
    tiny_model_dir: Path, tmp_path: Path
) -> None:
    backend = ClipSegBackend(str(tiny_model_dir), precision="auto", cache_dir=tmp_path, measure_now=False)
    asked: list[int] = []

    def cancel_after_the_first_mode() -> bool:
        asked.append(1)
        return len(asked) > 1

    with pytest.raises(precision_choice.MeasurementCancelled):
        precision_choice.measure_modes(
            backend, ["fp32", "int8", "ort-fp32"], runs=1, cancelled=cancel_after_the_first_mode
        )
    assert len(asked) == 2  # asked before fp32 (measured), then before int8 (stopped)

    cancel = threading.Event()
    cancel.set()
    precision_choice.measure_then_switch(backend, ["fp32", "int8"], cancel)
    assert backend.precision == "fp32" and not backend.measuring and not (tmp_path / "precision").exists()
