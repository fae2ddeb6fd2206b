"""Issue 60, item 1: the machine's floor for a frame (service/backends/floor.py) and its place in `gcdtrav doctor`."""

from __future__ import annotations

import argparse
import importlib.util
import re
from pathlib import Path

import pytest

pytest.importorskip("torch")

from gcdtrav.service.backends import precision_choice
from gcdtrav.service.backends.floor import (
    DecoderShape,
    FrameShape,
    TrunkShape,
    frame_shape,
    measure_floors,
    trunk_shape,
    upsampling_flops,
)
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


def test_the_decoder_products_of_rd64_refined_at_13_anchors() -> None:
    # width 64, MLP 2048, 3 layers, FiLM from the 512-wide text projection; 75.3 MFLOP of upsampling a concept
    upsampling = 2 * 22 * 22 * 64 * 64 * 9 + 2 * 22 * 22 * 64 * 32 * 16 + 2 * 88 * 88 * 32 * 1 * 16
    decoder = DecoderShape(485, 768, 64, 2048, 3, 512, upsampling)
    per_layer = 2 * 485 * 64 * (4 * 64 + 2 * 2048) + 2 * 2 * 485 * 485 * 64
    per_concept = 2 * 2 * 512 * 64 + 3 * per_layer + upsampling
    assert decoder.matmul_flops(13) == 2 * 485 * 768 * 64 * 3 + 13 * per_concept
    assert decoder.matmul_flops(13) / 1e9 == pytest.approx(14.0, abs=0.05)
    frame = FrameShape(TrunkShape(485, 768, 3072, 10), decoder, concepts=13)
    assert list(frame.parts) == ["vision transformer", "decoder and upsampling"]
    assert frame.matmul_flops / 1e9 == pytest.approx(75.9 + 14.0, abs=0.1)
    # one concept and none: the reductions run once a frame whatever the anchors
    assert decoder.matmul_flops(0) == 2 * 485 * 768 * 64 * 3
    assert decoder.matmul_flops(1) == decoder.matmul_flops(0) + per_concept


@pytest.mark.parametrize("refined", [True, False])
def test_the_upsampling_is_counted_as_the_layers_run_it(refined: bool) -> None:
    """Against the shapes torch's own forward pass produces (hooks), for CLIPSeg's two upsamplings."""
    import torch

    if refined:  # rd64-refined's: a 3x3 conv, then two transposed 4x4 of stride 4
        stack = torch.nn.Sequential(
            torch.nn.Conv2d(64, 64, 3, padding=1),
            torch.nn.ReLU(),
            torch.nn.ConvTranspose2d(64, 32, 4, stride=4),
            torch.nn.ReLU(),
            torch.nn.ConvTranspose2d(32, 1, 4, stride=4),
        )
    else:  # rd64's: one transposed 16x16 of stride 16
        stack = torch.nn.Sequential(torch.nn.ConvTranspose2d(64, 1, 16, stride=16))
    counted: list[float] = []

    def count(layer: torch.nn.Module, inputs: tuple[torch.Tensor], output: torch.Tensor) -> None:
        assert isinstance(layer, torch.nn.Conv2d | torch.nn.ConvTranspose2d)
        kernel = layer.kernel_size[0] * layer.kernel_size[1]
        positions = inputs[0].numel() // layer.in_channels if isinstance(layer, torch.nn.ConvTranspose2d) else None
        if positions is None:  # a convolution: every output gathers in_channels x kernel
            counted.append(2.0 * output.numel() * layer.in_channels * kernel)
        else:  # a transposed one: every input spreads over out_channels x kernel
            counted.append(2.0 * positions * layer.in_channels * layer.out_channels * kernel)

    for layer in stack:
        if isinstance(layer, torch.nn.Conv2d | torch.nn.ConvTranspose2d):
            layer.register_forward_hook(count)
    with torch.no_grad():
        image = stack(torch.zeros(1, 64, 22, 22))
    assert image.shape[-2:] == (352, 352)
    assert upsampling_flops(stack, 22) == pytest.approx(sum(counted), rel=1e-12)
    assert upsampling_flops(torch.nn.Sequential(torch.nn.ReLU()), 22) == 0.0


def test_the_frame_shape_is_read_from_the_model(tiny_model_dir: Path) -> None:
    from transformers import CLIPSegForImageSegmentation

    model = CLIPSegForImageSegmentation.from_pretrained(tiny_model_dir)
    config = model.config
    shape = frame_shape(model, tokens=17, concepts=3)
    assert shape.trunk == trunk_shape(config, tokens=17)
    decoder = shape.decoder
    assert (decoder.width, decoder.mlp, decoder.layers) == (
        config.reduce_dim,
        config.decoder_intermediate_size,
        len(config.extract_layers),
    )
    assert decoder.upsampling_flops == upsampling_flops(model.decoder.transposed_convolution, 4) > 0
    assert shape.matmul_flops == shape.trunk.matmul_flops + decoder.matmul_flops(3)


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
    floor_line = re.search(r"floor +([\d.]+) GFLOP of matrix products a frame \(13 anchors, (\d+) tokens: ", out)
    assert floor_line, out
    found = re.findall(r"^ +\w+ +\(\w+\) [\d,]+ G(?:FLOP|OP)/s -> ([\d.e+-]+) ms \(ViT ([\d.e+-]+)\)$", out, re.M)
    assert found, out
    floors_ms = [float(frame) for frame, _ in found]
    assert all(float(frame) > float(vit) > 0 for frame, vit in found)  # the decoder's products add to the ViT's
    assert "| mode | ms per frame | x floor |" in out
    rows = dict(re.findall(r"^\| (fp32|int8) \| \d+ \| ([\d.]+) \|", out, re.M))
    assert set(rows) == {"fp32", "int8"}
    assert float(rows["fp32"]) == pytest.approx(100.0 / min(floors_ms), rel=0.02, abs=0.1)
    assert float(rows["fp32"]) > float(rows["int8"])
