"""Issue 60, item 1: the machine's floor for a frame (service/backends/floor.py) and its place in `gcdtrav doctor`."""

from __future__ import annotations

import argparse
import importlib.util
import re
from pathlib import Path

import pytest

pytest.importorskip("torch")

from gcdtrav.service.backends import precision_choice
from gcdtrav.service.backends.floor import TrunkShape, measure_floors, trunk_shape
from gcdtrav.service.backends.precision_choice import ModeMeasurement
from gcdtrav.service.commands import doctor


def test_the_trunk_products_of_rd64_refined_are_the_issues_75_9_gflop() -> None:
    # ViT-B/16 at 352 px: 22 x 22 patches + the class token; layers 3, 6 and 9 read, so 10 run
    shape = TrunkShape(tokens=485, hidden=768, mlp=3072, layers=10)
    per_layer = 2 * 485 * 768 * (3 * 768 + 768 + 2 * 3072) + 2 * 2 * 485 * 485 * 768
    assert shape.matmul_flops == 10 * per_layer
    assert shape.matmul_flops / 1e9 == pytest.approx(75.9, abs=0.05)


def test_the_shape_is_read_from_the_models_config_up_to_the_last_layer_the_decoder_reads(tiny_model_dir: Path) -> None:
    from transformers import CLIPSegConfig

    config = CLIPSegConfig.from_pretrained(tiny_model_dir)
    shape = trunk_shape(config, tokens=17)
    assert shape.layers == max(config.extract_layers) + 1
    assert (shape.hidden, shape.mlp) == (config.vision_config.hidden_size, config.vision_config.intermediate_size)


def test_a_floor_for_each_arithmetic_asked_int8_only_with_onnxruntime() -> None:
    shape = TrunkShape(tokens=33, hidden=32, mlp=64, layers=2)
    floors = measure_floors(shape, {"fp32", "int8"}, threads=1)
    has_onnx = all(importlib.util.find_spec(name) for name in ("onnx", "onnxruntime"))
    assert [floor.arithmetic for floor in floors] == (["fp32", "int8"] if has_onnx else ["fp32"])
    for floor in floors:
        assert floor.operations_per_s > 0
        assert floor.ms(shape) == pytest.approx(1000 * shape.matmul_flops / floor.operations_per_s)
    assert measure_floors(shape, set(), threads=1) == []


def test_doctor_prints_the_floor_and_each_modes_multiple_of_it(
    tiny_model_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    figures = [ModeMeasurement("fp32", 100.0, 0.0), ModeMeasurement("int8", 40.0, 0.001)]
    monkeypatch.setattr(precision_choice, "measure_modes", lambda *args, **kwargs: figures)
    assert doctor.run(argparse.Namespace(model=str(tiny_model_dir), runs=1, cache_dir=tmp_path, measure=False)) == 0
    out = capsys.readouterr().out
    floor_line = re.search(r"floor +([\d.]+) GFLOP of ViT matrix products a frame \((\d+) layers, (\d+) tokens\)", out)
    assert floor_line, out
    floors_ms = [float(ms) for ms in re.findall(r"^ +\w+ +\(\w+\) [\d,]+ G(?:FLOP|OP)/s -> ([\d.e+-]+) ms$", out, re.M)]
    assert floors_ms, out
    assert "| mode | ms per frame | x floor |" in out
    rows = dict(re.findall(r"^\| (fp32|int8) \| \d+ \| ([\d.]+) \|", out, re.M))
    assert set(rows) == {"fp32", "int8"}
    assert float(rows["fp32"]) == pytest.approx(100.0 / min(floors_ms), rel=0.02, abs=0.1)
    assert float(rows["fp32"]) > float(rows["int8"])
