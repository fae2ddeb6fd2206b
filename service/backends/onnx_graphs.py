"""The fast path as two plain torch modules an ONNX exporter can trace: the ViT trunk and the batched decoder.

Same arithmetic as ``ClipSegBackend``'s torch path (the trunk stops after the last layer the decoder reads;
the decoder runs batched over concepts, FiLM broadcasting the one image's tokens), written with standard
ops only: oneDNN post-ops are unknown to exporters, and ONNX Runtime fuses what it recognises itself.

The decoder's linear layers take 2-D inputs (concepts x tokens, width): a 2-D ``linear`` exports as one
``Gemm``, which ONNX Runtime fuses with the following ReLU, where a 3-D one becomes MatMul, Add and Relu,
three passes over the (concepts x tokens x 2048) intermediate (measured: 27 of 170 ms on an AVX2 EPYC).
They are called as modules so the exported nodes carry their names (``.../mlp/fc1/Gemm``): the int8
decoder quantises the MLPs by name.

Attention, in the trunk and in the decoder, is one ``com.microsoft.MultiHeadAttention`` node: ONNX Runtime's
CPU kernel (MLAS flash attention) takes the projections as (batch, tokens, width), so the scores are never
written out and no head transposes run. Measured on a 2-core AVX512 EPYC against the exporter's
MatMul-Softmax-MatMul with its transposes: the int8 trunk 77.4 -> 73.0 ms, the int8 decoder (13 concepts)
45.3 -> 42.8 ms.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from gcdtrav.service.backends.decoder import PatchwiseUpsampler


class FusedAttention(torch.autograd.Function):
    """Multi-head scaled dot-product attention on (batch, tokens, width) projections, exported as one node."""

    @staticmethod
    def forward(ctx: Any, query: torch.Tensor, key: torch.Tensor, value: torch.Tensor, heads: int, scale: float) -> Any:
        batch, tokens, width = query.shape

        def split(projected: torch.Tensor) -> torch.Tensor:  # (b, L, d) -> (b, heads, L, d/heads)
            return projected.reshape(batch, tokens, heads, width // heads).transpose(1, 2)

        context = torch.nn.functional.scaled_dot_product_attention(split(query), split(key), split(value), scale=scale)
        return context.transpose(1, 2).reshape(batch, tokens, width)

    @staticmethod
    def symbolic(graph: Any, query: Any, key: Any, value: Any, heads: int, scale: float) -> Any:
        fused = graph.op("com.microsoft::MultiHeadAttention", query, key, value, num_heads_i=heads, scale_f=scale)
        return fused.setType(query.type())


def attention_context(attention: Any, rows: torch.Tensor, shape: Sequence[int]) -> torch.Tensor:
    """A transformers CLIP attention module's context for ``rows`` (its input in 2-D or 3-D), in ``shape``."""
    projections = (attention.q_proj(rows), attention.k_proj(rows), attention.v_proj(rows))
    query, key, value = (projected.reshape(shape) for projected in projections)
    return FusedAttention.apply(query, key, value, attention.num_heads, float(attention.scale))


class PatchEmbedding(torch.nn.Module):
    """CLIP's embeddings at ``size`` x ``size`` pixels: the patches' convolution (stride = kernel) as one matrix
    product over the image's patches, plus a constant (the class token, the positions interpolated to ``size``,
    the convolution's bias) computed once here. The int8 export quantises the product like every other: ONNX
    Runtime's fp32 Conv took 1.40 ms, the patches' transpose and the int8 MatMul 0.53 ms (2-core AVX512 EPYC)."""

    def __init__(self, embeddings: Any, size: int) -> None:
        super().__init__()
        convolution = embeddings.patch_embedding
        self.patch, channels, width = convolution.kernel_size[0], convolution.in_channels, convolution.out_channels
        tiles = tuple(convolution.stride) == tuple(convolution.kernel_size) == (self.patch, self.patch)
        plain = convolution.padding in ((0, 0), "valid") and tuple(convolution.dilation) == (1, 1)
        if not (tiles and plain and convolution.groups == 1) or size % self.patch:
            raise ValueError(
                f"a convolution of kernel {convolution.kernel_size}, stride {convolution.stride}, padding "
                f"{convolution.padding}, dilation {convolution.dilation} and {convolution.groups} group(s) does "
                f"not tile {size} px into patches"
            )
        self.grid = size // self.patch
        self.constant: torch.Tensor  # a buffer, registered below
        self.project = torch.nn.Linear(channels * self.patch * self.patch, width, bias=False)
        with torch.no_grad():
            self.project.weight.copy_(convolution.weight.reshape(width, -1))
            pixels = torch.zeros(1, channels, size, size, dtype=convolution.weight.dtype)
            self.register_buffer("constant", embeddings(pixels, interpolate_pos_encoding=True))

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        grid, patch, channels = self.grid, self.patch, pixels.shape[1]
        patches = pixels.reshape(1, channels, grid, patch, grid, patch).permute(0, 2, 4, 1, 3, 5)
        tokens = self.project(patches.reshape(1, grid * grid, channels * patch * patch))
        constant = self.constant
        return torch.cat([constant[:, :1], constant[:, 1:] + tokens], dim=1)


class TrunkGraph(torch.nn.Module):
    """pixels (1, 3, S, S) -> the hidden states after each of ``extract_layers``, each (1, L, D)."""

    def __init__(self, vision: Any, extract_layers: list[int], size: int) -> None:
        super().__init__()
        self.embeddings, self.pre_layrnorm = PatchEmbedding(vision.embeddings, size), vision.pre_layrnorm
        self.layers = torch.nn.ModuleList(list(vision.encoder.layers)[: max(extract_layers) + 1])
        self.extract_layers = set(extract_layers)

    def forward(self, pixels: torch.Tensor) -> tuple[torch.Tensor, ...]:
        hidden = self.pre_layrnorm(self.embeddings(pixels))
        kept = []
        for index, layer in enumerate(self.layers):
            hidden = self._layer(layer, hidden)
            if index in self.extract_layers:
                kept.append(hidden)
        return tuple(kept)

    @staticmethod
    def _layer(layer: Any, hidden: torch.Tensor) -> torch.Tensor:
        """CLIPEncoderLayer (pre-norm attention, then the MLP) on (1, L, D) tokens."""
        attention = layer.self_attn
        context = attention_context(attention, layer.layer_norm1(hidden), hidden.shape)
        hidden = hidden + attention.out_proj(context)
        return hidden + layer.mlp(layer.layer_norm2(hidden))


class ReductionGraph(torch.nn.Module):
    """(three activations (1, L, D)) -> the decoder's reductions of them, each (1, L, d), in the decoder's order
    (the last layer read first). Run once a frame: every run of the decoder over a chunk of concepts shares
    them (inside the decoder graph they were recomputed per chunk: 2.3 ms a frame of 13 concepts in 4 chunks)."""

    def __init__(self, decoder: Any) -> None:
        super().__init__()
        self.reduces = decoder.reduces

    def forward(self, first: torch.Tensor, second: torch.Tensor, third: torch.Tensor) -> tuple[torch.Tensor, ...]:
        activations = (third, second, first)
        return tuple(reduce(activation[0])[None] for activation, reduce in zip(activations, self.reduces, strict=True))


class DecoderGraph(torch.nn.Module):
    """(three reductions (1, L, d) from ``ReductionGraph``, conditional (n, P)) -> logits as ``FastDecoder``
    computes them, in the upsampler's nested blocks (``PatchwiseUpsampler.blocks``) where it has them, else
    (n, S, S).

    The blocks are put in image order outside the graph (``blocks_to_image``, once per frame): ONNX Runtime's
    8-D Transpose took 4.1 ms a frame for 13 concepts on a 2-core AVX512 EPYC, torch's permuting copy 1.1 ms."""

    def __init__(self, decoder: Any) -> None:
        super().__init__()
        self.decoder = decoder
        self.upsample = PatchwiseUpsampler(decoder.transposed_convolution)

    def forward(self, *reduced_and_conditional: torch.Tensor) -> Any:
        *reductions, conditional = reduced_and_conditional
        decoder = self.decoder
        output: torch.Tensor | None = None
        for index, (reduced, layer) in enumerate(zip(reductions, decoder.layers, strict=True)):
            output = reduced if output is None else reduced + output
            if index == decoder.conditional_layer:
                output = decoder.film_mul(conditional)[:, None, :] * output + decoder.film_add(conditional)[:, None, :]
            output = self._layer(layer, output)
        assert output is not None
        tokens = output[:, 1:, :].transpose(1, 2)
        side = round(float(tokens.shape[2]) ** 0.5)  # a constant when traced: the input size is fixed
        grid = tokens.reshape(tokens.shape[0], tokens.shape[1], side, side)
        if self.upsample.nests_blocks:
            return self.upsample.blocks(grid)
        return self.upsample(grid).squeeze(1)

    @staticmethod
    def _layer(layer: Any, hidden: torch.Tensor) -> torch.Tensor:
        """CLIPSegDecoderLayer (post-norm attention, then the ReLU MLP) on (n, L, d) tokens, linears in 2-D."""
        attention = layer.self_attn
        concepts, tokens, width = hidden.shape
        rows = hidden.reshape(concepts * tokens, width)
        context = attention_context(attention, rows, hidden.shape).reshape(concepts * tokens, width)
        rows = layer.layer_norm1(rows + attention.out_proj(context))
        mlp = layer.mlp
        expanded = mlp.activation_fn(mlp.fc1(rows))
        rows = layer.layer_norm2(rows + mlp.fc2(expanded))
        return rows.reshape(concepts, tokens, width)
