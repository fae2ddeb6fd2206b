"""What this machine offers the runtime modes (``modes.py``): native bf16, ONNX Runtime."""

from __future__ import annotations

from gcdtrav.service.backends.modes import Need, modes_with


def cpu_has_fast_bf16() -> bool:
    """AVX512-BF16 or AMX: bf16 matrix products run natively (x86). Elsewhere bf16 is emulated and slow."""
    import torch

    checks = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")
    return any(bool(getattr(torch.cpu, name, lambda: False)()) for name in checks)


def machine_has(need: Need) -> bool:
    if need == "native-bf16":
        return cpu_has_fast_bf16()
    from gcdtrav.service.backends.onnx_runtime import onnx_runtime_available

    return onnx_runtime_available()


def available_precisions() -> list[str]:
    """The concrete modes worth running on this machine: bf16 only where native, ONNX Runtime if installed."""
    return modes_with(machine_has)
