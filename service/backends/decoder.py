"""CLIPSeg's decoder, rearranged for a CPU: the same arithmetic as transformers' modules, fewer memory passes.

The decoder runs once per anchor (three post-norm transformer layers of width 64 with a 2048-wide MLP,
then an upsampler to the input size), so its cost is what an extra anchor costs. Two changes matter
on a CPU, both exact (tests compare with transformers' forward):

- the MLP's first linear layer and its ReLU are one oneDNN call (the post-op inductor also uses), so
  the (anchors x tokens x 2048) intermediate is written once instead of written, read and rewritten;
- the transposed convolutions whose kernel equals their stride (each input pixel paints its own block
  of output pixels) become matrix products on token-major data, instead of oneDNN's deconvolution.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, TypeGuard

import torch
from gcdtrav.service.backends.onednn import LinearReLU, linear_then_relu, measured_linear_relu

# Concepts per decoder run in torch (ONNX Runtime's: onnx_runtime.ORT_DECODER_CHUNK): the MLP's (concepts x
# tokens x 2048) intermediate stays small enough for the cache (measured best of 1, 2, 4, 8, all on 2 cores;
# benchmarks/README.md).
DECODER_CHUNK = 8


def decoder_layer(layer: Any, hidden: torch.Tensor, linear_relu: LinearReLU = linear_then_relu) -> torch.Tensor:
    """CLIPSegDecoderLayer.forward (post-norm attention, then MLP) with the MLP's ReLU fused."""
    residual = hidden
    hidden, _ = layer.self_attn(hidden_states=hidden, attention_mask=None)
    hidden = layer.layer_norm1(residual + hidden)
    mlp = layer.mlp
    if isinstance(mlp.activation_fn, torch.nn.ReLU):
        expanded = linear_relu(hidden, mlp.fc1)
    else:
        expanded = mlp.activation_fn(mlp.fc1(hidden))
    return layer.layer_norm2(hidden + mlp.fc2(expanded))


def _is_patchwise(module: torch.nn.Module) -> TypeGuard[torch.nn.ConvTranspose2d]:
    """A transposed convolution in which every input pixel owns a disjoint kernel-sized output block."""
    return (
        isinstance(module, torch.nn.ConvTranspose2d)
        and tuple(module.stride) == tuple(module.kernel_size)
        and tuple(module.padding) == (0, 0)
        and tuple(module.output_padding) == (0, 0)
        and tuple(module.dilation) == (1, 1)
        and module.groups == 1
    )


@dataclass(frozen=True)
class PatchwiseStep:
    """One stride-equals-kernel transposed convolution as a matrix: C channels to (kh, kw, C') per pixel."""

    matrix: torch.Tensor  # (C, kh * kw * C')
    bias: torch.Tensor  # (kh * kw * C',): the bias repeated for every output pixel of a block
    block: tuple[int, int]  # (kh, kw)
    out_channels: int
    relu: bool

    @classmethod
    def of(cls, conv: torch.nn.ConvTranspose2d, relu: bool) -> PatchwiseStep:
        kh, kw = conv.kernel_size
        # weight (C, C', kh, kw) -> (C, kh, kw, C') -> (C, kh * kw * C')
        matrix = conv.weight.detach().permute(0, 2, 3, 1).reshape(conv.in_channels, kh * kw * conv.out_channels)
        bias = conv.bias.detach() if conv.bias is not None else torch.zeros(conv.out_channels, dtype=matrix.dtype)
        return cls(matrix.contiguous(), bias.repeat(kh * kw), (kh, kw), conv.out_channels, relu)


class PatchwiseUpsampler:
    """The decoder's ``transposed_convolution`` with its stride-equals-kernel tail as matrix products.

    A leading part that is not of that kind (the refined model's 3x3 convolution and ReLU) runs as is.
    The tail keeps pixels token-major, (pixels, channels), so each transposed convolution is one
    ``addmm`` from C channels to (kh, kw, C') values per pixel, and the blocks are put in image order
    once at the end.
    """

    def __init__(self, upsampler: torch.nn.Module) -> None:
        modules = list(upsampler) if isinstance(upsampler, torch.nn.Sequential) else [upsampler]
        first = next((i for i, m in enumerate(modules) if _is_patchwise(m)), len(modules))
        tail = modules[first:]
        self.head = torch.nn.Sequential(*modules[:first])
        self.steps: list[PatchwiseStep] = []
        self.fallback: torch.nn.Module | None = None
        index = 0
        while index < len(tail):
            conv = tail[index]
            if not _is_patchwise(conv):
                self.fallback = upsampler  # an unexpected layout: run transformers' module unchanged
                return
            relu = index + 1 < len(tail) and isinstance(tail[index + 1], torch.nn.ReLU)
            self.steps.append(PatchwiseStep.of(conv, relu))
            index += 2 if relu else 1

    def __call__(self, grid: torch.Tensor) -> torch.Tensor:
        """(n, C, h, w) -> (n, C_out, h * prod(kh), w * prod(kw)), as the module would return."""
        if self.fallback is not None:
            return self.fallback(grid)
        return blocks_to_image(self.blocks(grid)) if self.nests_blocks else self.head(grid)

    @property
    def nests_blocks(self) -> bool:
        """Whether ``blocks`` applies: a stride-equals-kernel tail, and no fallback."""
        return self.fallback is None and bool(self.steps)

    def blocks(self, grid: torch.Tensor) -> torch.Tensor:
        """The tail's output before it is put in image order: (n, h, w, kh1, kw1, kh2, kw2, ..., C_out)."""
        grid = self.head(grid)
        n, channels, h, w = grid.shape
        values = grid.permute(0, 2, 3, 1).reshape(-1, channels)
        for step in self.steps:
            values = torch.addmm(step.bias, values, step.matrix)
            if step.relu:
                values = torch.relu_(values)
            values = values.reshape(-1, step.out_channels)  # one row per output pixel, blocks nested in pixels
        return values.reshape([n, h, w, *[size for step in self.steps for size in step.block], values.shape[1]])


def blocks_to_image(nested: torch.Tensor) -> torch.Tensor:
    """(n, h, w, kh1, kw1, ..., khk, kwk, C) -> (n, C, h * kh1 * ... * khk, w * kw1 * ... * kwk).

    Image rows are (h, kh1, kh2, ...) and columns (w, kw1, kw2, ...): one permuting copy."""
    n, h, w, *blocks, channels = nested.shape
    rows = [3 + 2 * i for i in range(len(blocks) // 2)]
    order = [0, nested.dim() - 1, 1, *rows, 2, *[row + 1 for row in rows]]
    height, width = h * math.prod(blocks[0::2]), w * math.prod(blocks[1::2])
    return nested.permute(order).reshape(n, channels, height, width)


class FastDecoder:
    """CLIPSegDecoder.forward for one image's activations and many conditional embeddings."""

    def __init__(self, decoder: Any, tokens: int) -> None:
        """``tokens``: the ViT's token count at this input size, for timing the fused ReLU on a real shape."""
        self.decoder = decoder
        self.linear_relu = measured_linear_relu(decoder.layers[0].mlp.fc1, DECODER_CHUNK * tokens)
        self.upsample = PatchwiseUpsampler(decoder.transposed_convolution)

    def __call__(self, activations: Sequence[torch.Tensor], conditional: torch.Tensor) -> torch.Tensor:
        """(n, h, w) logits for n conditional embeddings; ``activations`` are the ViT's (1, L, D) states."""
        decoder = self.decoder
        output: torch.Tensor | None = None
        for index, (activation, layer, reduce) in enumerate(
            zip(activations[::-1], decoder.layers, decoder.reduces, strict=True)
        ):
            reduced = reduce(activation)
            output = reduced if output is None else reduced + output
            if index == decoder.conditional_layer:
                # FiLM broadcasts the single image's tokens (1, L, d) to the n concepts (n, L, d).
                output = decoder.film_mul(conditional)[:, None, :] * output + decoder.film_add(conditional)[:, None, :]
            output = decoder_layer(layer, output, self.linear_relu)
        assert output is not None
        tokens = output[:, 1:, :].transpose(1, 2)
        side = round(tokens.shape[2] ** 0.5)
        grid = tokens.reshape(tokens.shape[0], tokens.shape[1], side, side)
        return self.upsample(grid).squeeze(1)
