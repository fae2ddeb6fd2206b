"""What every settings section shares: the error, the environment prefix, the precision modes, key chunks."""

from __future__ import annotations

import os
import re
import socket
from typing import Literal, get_args

ENV_PREFIX = "GCDTRAV_"

# How the model's arithmetic runs. fp32: torch, the reference. bf16: ViT and decoder in bfloat16 (native on
# AVX512-BF16/AMX only). bf16-vit: the ViT only. int8: torch's dynamic int8 ViT. ort-fp32: ONNX Runtime in
# fp32. ort-int8-vit: ONNX Runtime, dynamic int8 ViT, fp32 decoder. ort-int8: also the decoder's MLPs in int8.
# auto: the fastest mode that passes the parity gate, by measurement on this machine at start (cached).
Precision = Literal["auto", "fp32", "bf16", "bf16-vit", "int8", "ort-fp32", "ort-int8-vit", "ort-int8"]
PRECISIONS: tuple[str, ...] = get_args(Precision)
KEY_CHUNK = re.compile(r"^[^*$#?\s/]+$")


class SettingsError(ValueError):
    pass


def default_instance_name() -> str:
    return f"{socket.gethostname()}-{os.getpid()}"
