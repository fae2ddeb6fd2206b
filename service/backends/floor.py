"""This machine's floor for a frame (issue 60): the matrix products a frame runs, divided by the rate at which
this machine multiplies matrices of the model's own shape, for each arithmetic it can run.

The products are the model's, for one image and its concepts:
- the ViT trunk's: per layer the Q, K, V and output projections, the two MLP products and the attention's two
  token-by-token products, for the layers up to the last one the decoder reads (10 of 12 in rd64-refined);
- the decoder's: its reductions of the layers read (once a frame), then per concept FiLM and, per decoder
  layer, the same products at the decoder's width;
- the upsampling's: the convolutions from the token grid to the image, per concept.
The engine is left out (no matrix products), and so are normalisations, activations and the softmax: the floor
is what no runtime can beat, not an estimate of a frame. Every product counts at the one rate measured on the
ViT's MLP product (tokens x hidden x mlp), the best-shaped of them: the decoder's narrow products run slower on
every runtime, so this floor is lower than a per-shape one. Rates with the threads the caller set: fp32 and
bf16 by torch, int8 by ONNX Runtime's MatMulInteger (the op its dynamic quantization runs). Medians of a few
repeats: a floor, not a benchmark.
"""

from __future__ import annotations

import statistics
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from gcdtrav.service.backends.modes import Arithmetic
from gcdtrav.service.backends.timing import interleaved_ms

WARMUP, REPEATS = 2, 7


@dataclass(frozen=True)
class TrunkShape:
    tokens: int  # one per patch, plus the class token
    hidden: int
    mlp: int
    layers: int  # layers a frame runs: up to the last one the decoder reads

    @property
    def matmul_flops(self) -> float:
        """Floating-point operations (a multiply and an add each count one) of the products of the layers run."""
        projections = 2 * self.tokens * self.hidden * (4 * self.hidden + 2 * self.mlp)
        attention = 2 * 2 * self.tokens * self.tokens * self.hidden  # scores and the weighted values
        return float(self.layers * (projections + attention))


def trunk_shape(config: Any, tokens: int) -> TrunkShape:
    """The trunk's shape from a CLIPSeg config (``transformers.CLIPSegConfig``) at ``tokens`` tokens."""
    vision = config.vision_config
    layers = max(config.extract_layers) + 1
    return TrunkShape(tokens, int(vision.hidden_size), int(vision.intermediate_size), layers)


@dataclass(frozen=True)
class DecoderShape:
    tokens: int
    hidden: int  # the trunk's width, which the reductions take in
    width: int  # the decoder's (reduce_dim)
    mlp: int
    layers: int  # one per trunk layer read
    conditional: int  # FiLM's input: the text projection's width
    upsampling_flops: float  # the convolutions from the token grid to the image, for one concept

    def matmul_flops(self, concepts: int) -> float:
        reductions = 2 * self.tokens * self.hidden * self.width * self.layers  # once a frame, shared by concepts
        return reductions + concepts * (self.transformer_flops + self.upsampling_flops)

    @property
    def transformer_flops(self) -> float:
        """FiLM and the decoder layers' products, for one concept."""
        film = 2 * 2 * self.conditional * self.width  # a scale and a shift
        projections = 2 * self.tokens * self.width * (4 * self.width + 2 * self.mlp)
        attention = 2 * 2 * self.tokens * self.tokens * self.width
        return float(film + self.layers * (projections + attention))


@dataclass(frozen=True)
class FrameShape:
    """A frame's matrix products: the trunk, and the decoder and upsampling for ``concepts`` concepts."""

    trunk: TrunkShape
    decoder: DecoderShape
    concepts: int

    @property
    def parts(self) -> dict[str, float]:
        """FLOPs by stage, as ``gcdtrav bench`` names its stages."""
        return {
            "vision transformer": self.trunk.matmul_flops,
            "decoder and upsampling": self.decoder.matmul_flops(self.concepts),
        }

    @property
    def matmul_flops(self) -> float:
        return sum(self.parts.values())


def frame_shape(model: Any, tokens: int, concepts: int) -> FrameShape:
    """The frame's shape from a CLIPSeg model (``transformers.CLIPSegForImageSegmentation``): its config, and
    its upsampling convolutions as built (rd64-refined's three, or one)."""
    config = model.config
    decoder = DecoderShape(
        tokens,
        int(config.vision_config.hidden_size),
        int(config.reduce_dim),
        int(config.decoder_intermediate_size),
        len(config.extract_layers),
        int(config.projection_dim),
        upsampling_flops(model.decoder.transposed_convolution, round((tokens - 1) ** 0.5)),
    )
    return FrameShape(trunk_shape(config, tokens), decoder, concepts)


def upsampling_flops(upsampling: Any, side: int) -> float:
    """FLOPs of a stack of ``Conv2d`` and ``ConvTranspose2d`` (other layers cost none here) on a ``side`` x
    ``side`` grid, for one concept."""
    import torch

    flops, size = 0.0, side
    for layer in upsampling.modules():
        if not isinstance(layer, torch.nn.Conv2d | torch.nn.ConvTranspose2d):
            continue
        (kernel, _), (stride, _), (dilation, _) = layer.kernel_size, layer.stride, layer.dilation
        padding = _padding(layer, kernel, dilation)
        taps = layer.in_channels // layer.groups * layer.out_channels * kernel * kernel
        if isinstance(layer, torch.nn.ConvTranspose2d):  # each input position spreads over a kernel of outputs
            flops += 2.0 * size * size * taps
            size = (size - 1) * stride - 2 * padding + dilation * (kernel - 1) + layer.output_padding[0] + 1
        else:  # each output position gathers a kernel of inputs
            size = (size + 2 * padding - dilation * (kernel - 1) - 1) // stride + 1
            flops += 2.0 * size * size * taps
    return flops


def _padding(layer: Any, kernel: int, dilation: int) -> int:
    if layer.padding == "same":  # Conv2d only, stride 1
        return dilation * (kernel - 1) // 2
    return 0 if layer.padding == "valid" else int(layer.padding[0])


@dataclass(frozen=True)
class Floor:
    arithmetic: Arithmetic
    runtime: str
    operations_per_s: float  # of the model's own product shape, on this machine's threads

    def ms(self, shape: TrunkShape | FrameShape) -> float:
        return self.ms_of(shape.matmul_flops)

    def ms_of(self, flops: float) -> float:
        return 1000.0 * flops / self.operations_per_s


def _median_s(run: Callable[[], object]) -> float:
    return statistics.median(interleaved_ms({"product": run}, REPEATS, WARMUP)["product"]) / 1000.0


def _torch_rate(shape: TrunkShape, dtype_name: str) -> float:
    import torch

    dtype = getattr(torch, dtype_name)
    left = torch.randn(shape.tokens, shape.hidden, dtype=dtype)
    right = torch.randn(shape.hidden, shape.mlp, dtype=dtype)
    with torch.inference_mode():
        seconds = _median_s(lambda: torch.matmul(left, right))
    return 2.0 * shape.tokens * shape.hidden * shape.mlp / seconds


def _onnx_int8_rate(shape: TrunkShape, threads: int) -> float:
    import numpy as np
    import onnxruntime
    from onnx import TensorProto, helper, numpy_helper

    weights = np.random.default_rng(0).integers(-127, 128, (shape.hidden, shape.mlp), dtype=np.int8)
    graph = helper.make_graph(
        [helper.make_node("MatMulInteger", ["a", "b", "a_zero"], ["y"])],
        "product",
        [helper.make_tensor_value_info("a", TensorProto.UINT8, [shape.tokens, shape.hidden])],
        [helper.make_tensor_value_info("y", TensorProto.INT32, [shape.tokens, shape.mlp])],
        [numpy_helper.from_array(weights, "b"), numpy_helper.from_array(np.array(128, np.uint8), "a_zero")],
    )
    # IR version 8 (onnx 1.10), not the installed onnx's newest: an older onnxruntime refuses a newer IR
    # ("Unsupported model IR version: 14, max supported IR version: 13": onnx 1.23 beside onnxruntime 1.30).
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)], ir_version=8)
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads, options.inter_op_num_threads = threads, 1
    session = onnxruntime.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])
    activations = np.random.default_rng(1).integers(0, 256, (shape.tokens, shape.hidden), dtype=np.uint8)
    seconds = _median_s(lambda: session.run(None, {"a": activations}))
    return 2.0 * shape.tokens * shape.hidden * shape.mlp / seconds


def measure_floors(shape: TrunkShape, arithmetics: set[Arithmetic], threads: int) -> list[Floor]:
    """One floor per arithmetic in ``arithmetics`` this machine can measure (int8 needs onnxruntime and onnx)."""
    floors = []
    for arithmetic in sorted(arithmetics):
        if arithmetic == "int8":
            try:
                floors.append(Floor("int8", "onnxruntime", _onnx_int8_rate(shape, threads)))
            except ImportError:
                continue
        else:
            dtype = "float32" if arithmetic == "fp32" else "bfloat16"
            floors.append(Floor(arithmetic, "torch", _torch_rate(shape, dtype)))
    return floors
