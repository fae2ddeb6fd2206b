"""This machine's floor for a frame (issue 60): the matrix products a frame runs, each divided by the rate at which
this machine runs a product of its shape, for each arithmetic it can run.

The products are the model's, for one image and its concepts (``Product``):
- the ViT trunk's: per layer the Q, K, V and output projections, the two MLP products and the attention's two
  token-by-token products, for the layers up to the last one the decoder reads (10 of 12 in rd64-refined);
- the decoder's: its reductions of the layers read (once a frame), FiLM, and per decoder layer the same
  products at the decoder's width, for every concept;
- the upsampling's: the convolutions from the token grid to the image, as the matrix products they are.

Each product with weights is timed at its own shape (the model's 485 x 768 x 3072 runs near this CPU's peak,
the decoder's 64-wide ones well below it on any runtime): a lower bound for that product, not for a kernel
that fuses it with the next. Attention's token-by-token products count at the best rate measured: timed alone,
they would be bound by writing out the scores, which a fused kernel never does. The decoder's products are
timed batched over all concepts, their best case. ``peak_ms`` counts every product at the best rate, the
strictest floor. Normalisations, activations, softmax and the engine are left out: the floor is what no
runtime can beat, not an estimate of a frame. Rates with the threads the caller set (``measure_floors`` says
which runtime for which arithmetic); each shape at the fastest of a few repeats.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from gcdtrav.service.backends.modes import Arithmetic
from gcdtrav.service.backends.timing import interleaved_ms

WARMUP, REPEATS = 2, 15
VISION, DECODER = "vision transformer", "decoder and upsampling"  # the stages with products (gcdtrav bench's names)


@dataclass(frozen=True)
class Product:
    """``count`` products of (m x k) by (k x n) a frame runs; ``weights``: the right factor is the model's
    weights (else both are activations: attention's token-by-token products)."""

    stage: str
    name: str
    m: int
    k: int
    n: int
    count: int
    weights: bool = True

    @property
    def flops(self) -> float:
        """Floating-point operations: a multiply and an add each count one."""
        return 2.0 * self.count * self.m * self.k * self.n

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.m, self.k, self.n


def total_flops(products: Iterable[Product]) -> float:
    return sum(product.flops for product in products)


@dataclass(frozen=True)
class TrunkShape:
    tokens: int  # one per patch, plus the class token
    hidden: int
    mlp: int
    layers: int  # layers a frame runs: up to the last one the decoder reads
    patch_values: int = 0  # channels x patch x patch: the patch embedding's input per patch (0: left out)

    @property
    def products(self) -> list[Product]:
        tokens, hidden, layers = self.tokens, self.hidden, self.layers
        products = [
            Product(VISION, "patch embedding", tokens - 1, self.patch_values, hidden, 1),
            Product(VISION, "Q, K, V and output projections", tokens, hidden, hidden, 4 * layers),
            Product(VISION, "MLP in", tokens, hidden, self.mlp, layers),
            Product(VISION, "MLP out", tokens, self.mlp, hidden, layers),
            Product(VISION, "attention", tokens, hidden, tokens, 2 * layers, weights=False),  # all heads together
        ]
        return [product for product in products if product.k]

    @property
    def matmul_flops(self) -> float:
        return total_flops(self.products)


def trunk_shape(config: Any, tokens: int) -> TrunkShape:
    """The trunk's shape from a CLIPSeg config (``transformers.CLIPSegConfig``) at ``tokens`` tokens."""
    vision = config.vision_config
    layers = max(config.extract_layers) + 1
    patch_values = int(vision.num_channels) * int(vision.patch_size) ** 2
    return TrunkShape(tokens, int(vision.hidden_size), int(vision.intermediate_size), layers, patch_values)


@dataclass(frozen=True)
class DecoderShape:
    tokens: int
    hidden: int  # the trunk's width, which the reductions take in
    width: int  # the decoder's (reduce_dim)
    mlp: int
    layers: int  # one per trunk layer read
    conditional: int  # FiLM's input: the text projection's width
    upsampling: tuple[tuple[int, int, int], ...]  # (m, k, n) of each convolution's product, for one concept
    concepts: int

    @property
    def products(self) -> list[Product]:
        """Batched over the concepts; the reductions run once a frame, shared by every concept."""
        concepts, width, layers = self.concepts, self.width, self.layers
        rows = concepts * self.tokens
        products = [
            Product(DECODER, "reductions", self.tokens, self.hidden, width, layers),
            Product(DECODER, "FiLM", concepts, self.conditional, width, 2),
            Product(DECODER, "Q, K, V and output projections", rows, width, width, 4 * layers),
            Product(DECODER, "MLP in", rows, width, self.mlp, layers),
            Product(DECODER, "MLP out", rows, self.mlp, width, layers),
            Product(DECODER, "attention", self.tokens, width, self.tokens, 2 * layers * concepts, weights=False),
        ]
        for index, (m, k, n) in enumerate(self.upsampling):
            products.append(Product(DECODER, f"upsampling {index + 1}", concepts * m, k, n, 1))
        return [product for product in products if product.count and product.m]

    @property
    def matmul_flops(self) -> float:
        return total_flops(self.products)


@dataclass(frozen=True)
class FrameShape:
    """A frame's matrix products: the trunk's, and the decoder's and the upsampling's for its concepts."""

    trunk: TrunkShape
    decoder: DecoderShape

    @property
    def concepts(self) -> int:
        return self.decoder.concepts

    @property
    def products(self) -> list[Product]:
        return self.trunk.products + self.decoder.products

    @property
    def parts(self) -> dict[str, float]:
        """FLOPs by stage."""
        return {VISION: self.trunk.matmul_flops, DECODER: self.decoder.matmul_flops}

    @property
    def matmul_flops(self) -> float:
        return total_flops(self.products)


def frame_shape(model: Any, tokens: int, concepts: int) -> FrameShape:
    """The frame's shape from a CLIPSeg model (``transformers.CLIPSegForImageSegmentation``): its config, and
    its upsampling convolutions as built (rd64-refined's three, or rd64's one). The tokens but the class token
    form a square grid, as CLIPSeg's decoder takes them."""
    config = model.config
    grid = round((tokens - 1) ** 0.5)
    decoder = DecoderShape(
        tokens,
        int(config.vision_config.hidden_size),
        int(config.reduce_dim),
        int(config.decoder_intermediate_size),
        len(config.extract_layers),
        int(config.projection_dim),
        upsampling_products(model.decoder.transposed_convolution, (grid, grid)),
        concepts,
    )
    return FrameShape(trunk_shape(config, tokens), decoder)


def upsampling_products(upsampling: Any, grid: tuple[int, int]) -> tuple[tuple[int, int, int], ...]:
    """The (m, k, n) product of each ``Conv2d`` and ``ConvTranspose2d`` in ``upsampling`` (a module or a stack;
    other layers have none) on a ``grid`` (height, width), for one concept: a convolution gathers, for each
    output position, its kernel's inputs (m outputs, k = in x kernel, n = out); a transposed one spreads each
    input position over a kernel of outputs (m inputs, k = in, n = out x kernel)."""
    import torch

    products, size = [], grid
    for layer in upsampling.modules():
        if not isinstance(layer, torch.nn.Conv2d | torch.nn.ConvTranspose2d):
            continue
        kernel, inputs = math.prod(layer.kernel_size), layer.in_channels // layer.groups
        if isinstance(layer, torch.nn.ConvTranspose2d):
            products.append((math.prod(size), inputs, layer.out_channels * kernel))
            size = _transposed_output(layer, size)
        else:
            size = _convolution_output(layer, size)
            products.append((math.prod(size), inputs * kernel, layer.out_channels))
    return tuple(products)


def _convolution_output(layer: Any, size: tuple[int, int]) -> tuple[int, int]:
    if layer.padding == "same":
        return size
    padding = (0, 0) if layer.padding == "valid" else layer.padding
    height, width = (
        (size[axis] + 2 * padding[axis] - layer.dilation[axis] * (layer.kernel_size[axis] - 1) - 1)
        // layer.stride[axis]
        + 1
        for axis in (0, 1)
    )
    return height, width


def _transposed_output(layer: Any, size: tuple[int, int]) -> tuple[int, int]:
    height, width = (
        (size[axis] - 1) * layer.stride[axis]
        - 2 * layer.padding[axis]
        + layer.dilation[axis] * (layer.kernel_size[axis] - 1)
        + layer.output_padding[axis]
        + 1
        for axis in (0, 1)
    )
    return height, width


@dataclass(frozen=True)
class Floor:
    arithmetic: Arithmetic
    runtime: str
    rates: dict[tuple[int, int, int], float]  # operations per second, by the (m, k, n) of a product with weights

    @property
    def peak(self) -> float:
        return max(self.rates.values())

    def rate(self, product: Product) -> float:
        return self.rates[product.shape] if product.weights else self.peak

    def ms(self, shape: TrunkShape | FrameShape) -> float:
        return sum(self.stage_ms(shape).values())

    def stage_ms(self, shape: TrunkShape | FrameShape) -> dict[str, float]:
        stages: dict[str, float] = {}
        for product in shape.products:
            stages[product.stage] = stages.get(product.stage, 0.0) + 1000.0 * product.flops / self.rate(product)
        return stages

    def peak_ms(self, shape: TrunkShape | FrameShape) -> float:
        return 1000.0 * shape.matmul_flops / self.peak


def _rates(
    shapes: list[tuple[int, int, int]], product: Callable[[int, int, int], Callable[[], object]]
) -> dict[tuple[int, int, int], float]:
    """Operations per second of each shape, one shape after another (its operands stay in cache, as a kernel
    would have them at best), each at the fastest of its repeats: noise only ever slows a product down, and
    the floor is the machine's best."""
    rates = {}
    for m, k, n in shapes:
        times = interleaved_ms({"product": product(m, k, n)}, REPEATS, WARMUP)["product"]
        rates[(m, k, n)] = 2.0 * m * k * n / (min(times) / 1000.0)
    return rates


def _torch_product(dtype_name: str) -> Callable[[int, int, int], Callable[[], object]]:
    import torch

    dtype = getattr(torch, dtype_name)

    def product(m: int, k: int, n: int) -> Callable[[], object]:
        left, right = torch.randn(m, k, dtype=dtype), torch.randn(k, n, dtype=dtype)

        def run() -> object:
            with torch.inference_mode():
                return torch.matmul(left, right)

        return run

    return product


def _onnx_product(threads: int, arithmetic: Arithmetic) -> Callable[[int, int, int], Callable[[], object]]:
    """ONNX Runtime's product in int8 (MatMulInteger, the op its dynamic quantization runs) or fp32 (MatMul)."""
    import numpy as np
    import onnxruntime
    from onnx import TensorProto, helper, numpy_helper

    int8 = arithmetic == "int8"

    def product(m: int, k: int, n: int) -> Callable[[], object]:
        rng = np.random.default_rng(0)
        if int8:
            weights = rng.integers(-127, 128, (k, n), dtype=np.int8)
            node = helper.make_node("MatMulInteger", ["a", "b", "a_zero"], ["y"])
            constants = [
                numpy_helper.from_array(weights, "b"),
                numpy_helper.from_array(np.array(128, np.uint8), "a_zero"),
            ]
            activations = rng.integers(0, 256, (m, k), dtype=np.uint8)
        else:
            node = helper.make_node("MatMul", ["a", "b"], ["y"])
            constants = [numpy_helper.from_array(rng.standard_normal((k, n)).astype(np.float32), "b")]
            activations = rng.standard_normal((m, k)).astype(np.float32)
        graph = helper.make_graph(
            [node],
            "product",
            [helper.make_tensor_value_info("a", TensorProto.UINT8 if int8 else TensorProto.FLOAT, [m, k])],
            [helper.make_tensor_value_info("y", TensorProto.INT32 if int8 else TensorProto.FLOAT, [m, n])],
            constants,
        )
        # IR version 8 (onnx 1.10), not the installed onnx's newest: an older onnxruntime refuses a newer IR
        # ("Unsupported model IR version: 14, max supported IR version: 13": onnx 1.23 beside onnxruntime 1.30).
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)], ir_version=8)
        # Not onnx_runtime.session_options: a product timed alone keeps its threads spinning, the machine's best
        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads, options.inter_op_num_threads = threads, 1
        session = onnxruntime.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])
        return lambda: session.run(None, {"a": activations})

    return product


def measure_floors(shape: TrunkShape | FrameShape, arithmetics: set[Arithmetic], threads: int) -> list[Floor]:
    """One floor per arithmetic in ``arithmetics`` this machine can measure, from the rate of each shape of
    product with weights in ``shape``: int8 by ONNX Runtime (left out without onnxruntime and onnx), bf16 by
    torch, fp32 by the faster of torch and ONNX Runtime for each shape (torch's MKL runs fp32 products at less
    than half ONNX Runtime's rate on an AMD EPYC). ONNX Runtime runs ``threads`` threads, torch the number it
    was set to (the caller sets both alike)."""
    shapes = sorted({product.shape for product in shape.products if product.weights})
    floors = []
    for arithmetic in sorted(arithmetics):
        if arithmetic == "bf16":
            floors.append(Floor("bf16", "torch", _rates(shapes, _torch_product("bfloat16"))))
            continue
        try:
            onnx_rates = _rates(shapes, _onnx_product(threads, arithmetic))
        except ImportError:
            onnx_rates = {}
        if arithmetic == "int8":
            if onnx_rates:
                floors.append(Floor("int8", "onnxruntime", onnx_rates))
            continue
        torch_rates = _rates(shapes, _torch_product("float32"))
        rates = {each: max(rate, onnx_rates.get(each, 0.0)) for each, rate in torch_rates.items()}
        floors.append(Floor("fp32", "torch, onnxruntime" if onnx_rates else "torch", rates))
    return floors
