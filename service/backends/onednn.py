"""Linear layers with their activation fused, through the oneDNN post-ops torch ships for inductor.

An MLP's hidden layer is its largest tensor; applying the activation inside the matrix product writes it
once instead of writing, reading and rewriting it. Each helper probes the op once for a dtype and falls
back to the plain modules where this torch build lacks it (non-x86 CPUs, builds without oneDNN).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
import torch.nn.functional as F
from gcdtrav.service.backends.timing import interleaved_ms

LinearReLU = Callable[[torch.Tensor, torch.nn.Linear], torch.Tensor]

# transformers' QuickGELUActivation: x * sigmoid(1.702 x), which is swish(1.702 x) / 1.702.
QUICK_GELU_SLOPE = 1.702
FUSION_TIMING_ROUNDS = 3


def _linear_pointwise(hidden: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, attr: str) -> torch.Tensor:
    return torch.ops.mkldnn._linear_pointwise(hidden, weight, bias, attr, [], "")


def onednn_has(attr: str, dtype: torch.dtype) -> bool:
    """Whether oneDNN's linear with post-op ``attr`` runs for ``dtype`` here and computes what it should."""
    probe = torch.tensor([[-1.0, 0.5, 2.0]], dtype=dtype)
    weight, bias = torch.eye(3, dtype=dtype), torch.zeros(3, dtype=dtype)
    expected = {"relu": torch.relu, "swish": F.silu}[attr](probe.float())
    try:
        out = _linear_pointwise(probe, weight, bias, attr)
    except (AttributeError, RuntimeError, NotImplementedError):
        return False
    return bool(torch.allclose(out.float(), expected, atol=1e-2))


def linear_then_relu(hidden: torch.Tensor, linear: torch.nn.Linear) -> torch.Tensor:
    return torch.relu_(linear(hidden))


def _linear_relu_onednn(hidden: torch.Tensor, linear: torch.nn.Linear) -> torch.Tensor:
    assert linear.bias is not None
    return _linear_pointwise(hidden, linear.weight, linear.bias, "relu")


def fused_linear_relu(dtype: torch.dtype) -> LinearReLU:
    """``relu(linear(x))`` as one oneDNN call where available for ``dtype``, else the two modules."""
    return _linear_relu_onednn if onednn_has("relu", dtype) else linear_then_relu


class QuickGeluMLP:
    """A CLIP layer's ``mlp(layer_norm2(x))`` with quick-GELU as oneDNN's swish post-op.

    x * sigmoid(1.702 x) = swish(1.702 x) / 1.702, so the norm's affine parameters and fc1's bias are
    scaled by 1.702 (small copies) and fc2's product by 1 / 1.702 (addmm's alpha); the large weight
    matrices are shared with the model, unchanged.
    """

    def __init__(self, norm: torch.nn.LayerNorm, mlp: Any) -> None:
        assert norm.weight is not None and norm.bias is not None and mlp.fc1.bias is not None
        self.shape, self.eps = tuple(norm.normalized_shape), norm.eps
        self.norm_weight = self._scaled(norm.weight)
        self.norm_bias = self._scaled(norm.bias)
        self.fc1_weight, self.fc1_bias = mlp.fc1.weight.detach(), self._scaled(mlp.fc1.bias)
        self.fc2_weight_t, self.fc2_bias = mlp.fc2.weight.detach().t(), mlp.fc2.bias.detach()

    @staticmethod
    def _scaled(values: torch.Tensor) -> torch.Tensor:
        return (values.detach().float() * QUICK_GELU_SLOPE).to(values.dtype)  # one rounding, in float32

    @classmethod
    def build(cls, norm: Any, mlp: Any, dtype: torch.dtype) -> QuickGeluMLP | None:
        """The fused MLP where it applies (plain linear layers, quick-GELU, oneDNN's swish), else None."""
        plain = all(type(m) is torch.nn.Linear and m.bias is not None for m in (mlp.fc1, mlp.fc2))
        quick_gelu = type(mlp.activation_fn).__name__ == "QuickGELUActivation"
        if not (plain and quick_gelu and isinstance(norm, torch.nn.LayerNorm) and onednn_has("swish", dtype)):
            return None
        return cls(norm, mlp)

    def __call__(self, hidden: torch.Tensor) -> torch.Tensor:
        normed = F.layer_norm(hidden, self.shape, self.norm_weight, self.norm_bias, self.eps)
        expanded = _linear_pointwise(normed, self.fc1_weight, self.fc1_bias, "swish")  # 1.702 x quick-GELU
        flat = expanded.reshape(-1, expanded.shape[-1])
        out = torch.addmm(self.fc2_bias, flat, self.fc2_weight_t, alpha=1.0 / QUICK_GELU_SLOPE)
        return out.reshape(*hidden.shape[:-1], out.shape[-1])


def runs_faster(first: Callable[[], object], second: Callable[[], object], rounds: int = FUSION_TIMING_ROUNDS) -> bool:
    """Whether ``first`` is faster than ``second`` on this CPU: best of ``rounds`` interleaved calls after a
    warm-up round (best, not median: a busy machine only ever adds time)."""
    with torch.inference_mode():
        times = interleaved_ms({"first": first, "second": second}, rounds)
    return min(times["first"]) < min(times["second"])


def _sample(rows: int, width: int, dtype: torch.dtype) -> torch.Tensor:
    return torch.randn(rows, width, generator=torch.Generator().manual_seed(0)).to(dtype)


def fused_mlp_pays(layer: Any, fused: QuickGeluMLP, tokens: int) -> bool:
    """Whether ``fused`` beats the layer's own ``mlp(layer_norm2(x))`` here, timed on (1, tokens, width).

    Measured, not assumed: oneDNN's fused bf16 MLP wins on an AMX Xeon, while on an AVX2-only EPYC its fp32
    matrix product is slower than torch's own (fp32 trunk 566 against 489 ms per frame).
    """
    norm = layer.layer_norm2
    sample = _sample(tokens, norm.normalized_shape[0], norm.weight.dtype)[None]
    return runs_faster(lambda: fused(sample), lambda: layer.mlp(norm(sample)))


def measured_linear_relu(linear: torch.nn.Linear, rows: int) -> LinearReLU:
    """``fused_linear_relu`` where it is faster than the two modules on (rows, in_features) here (on an
    AVX2-only EPYC it is not: the fp32 decoder 141 against 132 ms for 13 anchors)."""
    fused = fused_linear_relu(linear.weight.dtype)
    if fused is linear_then_relu:
        return fused
    sample = _sample(rows, linear.in_features, linear.weight.dtype)
    return (
        fused
        if runs_faster(lambda: fused(sample, linear), lambda: linear_then_relu(sample, linear))
        else linear_then_relu
    )


def clip_encoder_layer(layer: Any, hidden: torch.Tensor, mlp: QuickGeluMLP | None) -> torch.Tensor:
    """CLIPSegEncoderLayer.forward (pre-norm attention, then pre-norm MLP), with the fused MLP if given."""
    if mlp is None:
        return layer(hidden, None)
    attended, _ = layer.self_attn(hidden_states=layer.layer_norm1(hidden), attention_mask=None)
    hidden = hidden + attended
    return hidden + mlp(hidden)
