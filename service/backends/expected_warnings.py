"""Warnings torch gives for what gcdtrav does on purpose, silenced only around the calls that give them.

- dynamic int8 (``torch.ao.quantization.quantize_dynamic``): torch deprecates eager quantisation and its
  quantized tensors; the int8 mode is measured for speed and parity on each machine (``gcdtrav doctor``), and a
  torch without it fails the mode, which auto then skips;
- the ONNX export: the TorchScript exporter is chosen on purpose (``dynamo=False``), and its tracer warns that
  Python values (the fixed input size, the vision model's ``is_causal``) become constants, which they are;
  every export is checked against torch before it is used (onnx_runtime.py).

Any other warning still reaches the user. ``warnings.catch_warnings`` is process-wide: a warning another thread
gives during these calls of a few seconds at start-up could be lost, none of ours is expected there.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from contextlib import contextmanager

import torch

EXPECTED = (
    (DeprecationWarning, r"torch\.ao\.quantization is deprecated"),
    (UserWarning, r"torch\.quantize_per_tensor, torch\.quantize_per_channel and other quantized tensor"),
    (DeprecationWarning, r"You are using the legacy TorchScript-based ONNX export"),
    (DeprecationWarning, r"The feature will be removed"),  # the TorchScript exporter's logging set-up
)


@contextmanager
def expected_torch_warnings(tracing: bool = False) -> Iterator[None]:
    """Silence ``EXPECTED`` (and, ``tracing``, torch's TracerWarnings) inside the block, nothing else."""
    with warnings.catch_warnings():
        for category, message in EXPECTED:
            warnings.filterwarnings("ignore", message=message, category=category)
        if tracing:
            warnings.filterwarnings("ignore", category=torch.jit.TracerWarning)
        yield
