"""Issue 60, item 1: the machine's floor for a frame (service/backends/floor.py) and its place in `gcdtrav doctor`."""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import re
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from gcdtrav.service.backends import precision_choice  # noqa: E402
from gcdtrav.service.backends.floor import (  # noqa: E402
    DECODER,
    VISION,
    DecoderShape,
    Floor,
    FrameShape,
    Product,
    TrunkShape,
    frame_shape,
    measure_floors,
    trunk_shape,
    upsampling_products,
)
from gcdtrav.service.backends.precision_choice import ModeMeasurement  # noqa: E402
from gcdtrav.service.commands import doctor  # noqa: E402

# rd64-refined's upsampling on its 22 x 22 grid: a 3x3 convolution 64 -> 64, then two transposed 4x4 of stride 4
RD64_UPSAMPLING = ((22 * 22, 64 * 9, 64), (22 * 22, 64, 32 * 16), (88 * 88, 32, 1 * 16))
# ViT-B/16 at 352 px: 22 x 22 patches + the class token; layers 3, 6 and 9 read, so 10 run; RGB patches of 16 x 16
RD64_TRUNK = TrunkShape(tokens=485, hidden=768, mlp=3072, layers=10, patch_values=3 * 16 * 16)


def rd64_refined(concepts: int = 13) -> FrameShape:
    return FrameShape(RD64_TRUNK, DecoderShape(485, 768, 64, 2048, 3, 512, RD64_UPSAMPLING, concepts))


def test_the_trunk_products_of_rd64_refined_are_the_issues_75_9_gflop_and_the_patch_embedding() -> None:
    per_layer = 2 * 485 * 768 * (3 * 768 + 768 + 2 * 3072) + 2 * 2 * 485 * 485 * 768
    layers_only = dataclasses.replace(RD64_TRUNK, patch_values=0)
    assert layers_only.matmul_flops == 10 * per_layer
    assert layers_only.matmul_flops / 1e9 == pytest.approx(75.9, abs=0.05)  # the issue's figure
    assert RD64_TRUNK.matmul_flops == 10 * per_layer + 2 * 484 * 768 * 768  # one product per patch
    assert RD64_TRUNK.products[0].name == "patch embedding"


def test_the_decoder_products_of_rd64_refined_at_13_anchors() -> None:
    # width 64, MLP 2048, 3 layers, FiLM from the 512-wide text projection; 75.3 MFLOP of upsampling a concept
    upsampling = 2 * 22 * 22 * 64 * 64 * 9 + 2 * 22 * 22 * 64 * 32 * 16 + 2 * 88 * 88 * 32 * 1 * 16
    decoder = rd64_refined().decoder
    per_layer = 2 * 485 * 64 * (4 * 64 + 2 * 2048) + 2 * 2 * 485 * 485 * 64
    per_concept = 2 * 2 * 512 * 64 + 3 * per_layer + upsampling
    reductions = 2 * 485 * 768 * 64 * 3
    assert decoder.matmul_flops == reductions + 13 * per_concept
    assert decoder.matmul_flops / 1e9 == pytest.approx(14.0, abs=0.05)
    frame = rd64_refined()
    assert frame.concepts == 13 and list(frame.parts) == [VISION, DECODER]
    assert frame.matmul_flops == sum(frame.parts.values())
    assert frame.matmul_flops / 1e9 == pytest.approx(76.45 + 14.0, abs=0.1)
    # one concept and none: the reductions run once a frame whatever the anchors
    assert dataclasses.replace(decoder, concepts=0).matmul_flops == reductions
    assert dataclasses.replace(decoder, concepts=1).matmul_flops == reductions + per_concept


def record_products(stack: torch.nn.Module, grid: tuple[int, int]) -> list[tuple[int, int, int]]:
    """The (m, k, n) of each convolution as torch's own forward pass shapes it (hooks)."""
    seen: list[tuple[int, int, int]] = []

    def record(layer: torch.nn.Module, inputs: tuple[torch.Tensor], output: torch.Tensor) -> None:
        assert isinstance(layer, torch.nn.Conv2d | torch.nn.ConvTranspose2d)
        kernel, group = layer.kernel_size[0] * layer.kernel_size[1], layer.in_channels // layer.groups
        if isinstance(layer, torch.nn.ConvTranspose2d):  # every input position spreads over out x kernel
            seen.append((inputs[0].shape[-2] * inputs[0].shape[-1], group, layer.out_channels * kernel))
        else:  # every output position gathers its group's inputs x kernel
            seen.append((output.shape[-2] * output.shape[-1], group * kernel, layer.out_channels))

    for layer in stack.modules():
        if isinstance(layer, torch.nn.Conv2d | torch.nn.ConvTranspose2d):
            layer.register_forward_hook(record)
    with torch.no_grad():
        stack(torch.zeros(1, 64, *grid))
    return seen


def test_the_upsampling_products_are_the_layers_as_run() -> None:
    """CLIPSeg's two upsamplings (rd64-refined's stack, rd64's one bare module), a non-square one, 'same'
    padding and an output padding, against the shapes torch's forward pass gives."""
    refined = torch.nn.Sequential(
        torch.nn.Conv2d(64, 64, 3, padding=1),
        torch.nn.ReLU(),
        torch.nn.ConvTranspose2d(64, 32, 4, stride=4),
        torch.nn.ReLU(),
        torch.nn.ConvTranspose2d(32, 1, 4, stride=4),
    )
    assert upsampling_products(refined, (22, 22)) == tuple(record_products(refined, (22, 22))) == RD64_UPSAMPLING
    plain = torch.nn.ConvTranspose2d(64, 1, 16, stride=16)
    assert upsampling_products(plain, (22, 22)) == ((484, 64, 256),) == tuple(record_products(plain, (22, 22)))
    odd = torch.nn.Sequential(
        torch.nn.Conv2d(64, 32, (3, 5), padding="same", dilation=(1, 2)),
        torch.nn.Conv2d(32, 32, (3, 1), stride=(2, 1), padding=(1, 0), groups=4),
        torch.nn.ConvTranspose2d(32, 8, (2, 3), stride=(2, 3), output_padding=(1, 0), dilation=1),
    )
    assert upsampling_products(odd, (9, 14)) == tuple(record_products(odd, (9, 14)))
    assert upsampling_products(torch.nn.Sequential(torch.nn.ReLU()), (22, 22)) == ()


def test_the_frame_shape_is_read_from_the_model(tiny_model_dir: Path) -> None:
    from transformers import CLIPSegForImageSegmentation

    model = CLIPSegForImageSegmentation.from_pretrained(tiny_model_dir)
    config = model.config
    shape = frame_shape(model, tokens=17, concepts=3)
    assert shape.trunk == trunk_shape(config, tokens=17)
    assert shape.trunk.layers == max(config.extract_layers) + 1
    vision = config.vision_config
    assert (shape.trunk.hidden, shape.trunk.mlp) == (vision.hidden_size, vision.intermediate_size)
    assert shape.trunk.patch_values == vision.num_channels * vision.patch_size**2
    decoder = shape.decoder
    assert (decoder.width, decoder.mlp, decoder.layers, decoder.concepts) == (
        config.reduce_dim,
        config.decoder_intermediate_size,
        len(config.extract_layers),
        3,
    )
    assert decoder.upsampling == upsampling_products(model.decoder.transposed_convolution, (4, 4)) != ()
    assert shape.matmul_flops == shape.trunk.matmul_flops + decoder.matmul_flops


def test_each_product_counts_at_its_shapes_rate_attention_at_the_best() -> None:
    """The floor from given rates: each product with weights at its shape's rate, attention's at the best;
    the floor at peak every product at the best; stages add up to the whole."""
    shape = rd64_refined()
    products = shape.products
    shapes = {product.shape for product in products if product.weights}
    slow = (13 * 485, 64, 2048)  # the decoder's MLP in, batched over 13 concepts
    assert slow in shapes
    rates = {each: 1e12 for each in shapes} | {slow: 2.5e11}
    floor = Floor("int8", "onnxruntime", rates)
    assert floor.peak == 1e12
    by_hand = sum(p.flops / (2.5e11 if p.shape == slow and p.weights else 1e12) for p in products) * 1000
    assert floor.ms(shape) == pytest.approx(by_hand, rel=1e-12)
    assert floor.peak_ms(shape) == pytest.approx(1000 * shape.matmul_flops / 1e12, rel=1e-12)
    assert floor.ms(shape) > floor.peak_ms(shape)
    stages = floor.stage_ms(shape)
    assert list(stages) == [VISION, DECODER] and sum(stages.values()) == pytest.approx(floor.ms(shape))
    assert stages[VISION] == pytest.approx(1000 * shape.trunk.matmul_flops / 1e12)  # all its shapes at peak here
    attention = [p for p in products if not p.weights]
    assert {p.name for p in attention} == {"attention"} and all(floor.rate(p) == 1e12 for p in attention)


def test_a_floor_for_each_arithmetic_asked_int8_only_with_onnxruntime() -> None:
    shape = TrunkShape(tokens=33, hidden=32, mlp=64, layers=2)
    floors = measure_floors(shape, {"fp32", "int8"}, threads=1)
    has_onnx = all(importlib.util.find_spec(name) for name in ("onnx", "onnxruntime"))
    assert [floor.arithmetic for floor in floors] == (["fp32", "int8"] if has_onnx else ["fp32"])
    if has_onnx:
        assert floors[0].runtime == "torch, onnxruntime"
    for floor in floors:
        assert set(floor.rates) == {(33, 32, 32), (33, 32, 64), (33, 64, 32)}  # the shapes with weights
        assert min(floor.rates.values()) > 0
        assert floor.ms(shape) >= floor.peak_ms(shape) > 0
    assert measure_floors(shape, set(), threads=1) == []
    assert Product(VISION, "empty", 0, 8, 8, 1).flops == 0.0


def test_fp32_takes_the_faster_runtime_for_each_shape(monkeypatch: pytest.MonkeyPatch) -> None:
    """Rates made up per runtime (each 'product' returns its rate): fp32 the larger per shape, bf16 torch's,
    int8 ONNX Runtime's."""
    from gcdtrav.service.backends import floor as floors_module

    torch_rates = {(33, 32, 32): 5.0, (33, 32, 64): 1.0, (33, 64, 32): 3.0}
    onnx_rates = {(33, 32, 32): 2.0, (33, 32, 64): 4.0, (33, 64, 32): 3.0}
    monkeypatch.setattr(floors_module, "_rates", lambda shapes, product: {s: product(*s)() for s in shapes})
    monkeypatch.setattr(floors_module, "_torch_product", lambda dtype: lambda *s: lambda: torch_rates[s])
    monkeypatch.setattr(floors_module, "_onnx_product", lambda threads, arithmetic: lambda *s: lambda: onnx_rates[s])
    shape = TrunkShape(tokens=33, hidden=32, mlp=64, layers=2)
    floors = {floor.arithmetic: floor for floor in measure_floors(shape, {"fp32", "bf16", "int8"}, threads=1)}
    fp32, bf16, int8 = floors["fp32"], floors["bf16"], floors["int8"]
    assert fp32.rates == {(33, 32, 32): 5.0, (33, 32, 64): 4.0, (33, 64, 32): 3.0}
    assert bf16.rates == torch_rates and int8.rates == onnx_rates


def test_doctor_prints_the_floor_and_each_modes_multiple_of_it(
    tiny_model_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    figures = [ModeMeasurement("fp32", 100.0, 0.0), ModeMeasurement("int8", 40.0, 0.001)]
    monkeypatch.setattr(precision_choice, "measure_modes", lambda *args, **kwargs: figures)
    assert doctor.run(argparse.Namespace(model=str(tiny_model_dir), runs=1, cache_dir=tmp_path, measure=False)) == 0
    out = capsys.readouterr().out
    floor_line = re.search(r"floor +([\d.]+) GFLOP of matrix products a frame \(13 anchors, (\d+) tokens: ", out)
    assert floor_line, out
    number = r"([\d.e+-]+)"
    line = rf"^ +\w+ +\([\w, ]+\) -> {number} ms \(vision transformer {number}, decoder and upsampling {number}\); "
    found = re.findall(line + rf"all at its best rate, [\d,]+ G(?:FLOP|OP)/s: {number} ms$", out, re.M)
    assert found, out
    floors_ms = [float(frame) for frame, *_ in found]
    for frame, vision, decoder, peak in found:
        assert float(frame) == pytest.approx(float(vision) + float(decoder), rel=0.01)
        assert float(frame) >= float(peak) > 0
    assert "| mode | ms per frame | x floor |" in out
    rows = dict(re.findall(r"^\| (fp32|int8) \| \d+ \| ([\d.]+) \|", out, re.M))
    assert set(rows) == {"fp32", "int8"}
    assert float(rows["fp32"]) == pytest.approx(100.0 / min(floors_ms), rel=0.02, abs=0.1)
    assert float(rows["fp32"]) > float(rows["int8"])
