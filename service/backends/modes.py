"""The runtime modes (``precision``): one table that every caller reads instead of matching mode names.

Each concrete mode says which runtime runs it, the arithmetic of the ViT trunk and of the decoder, and what
the machine needs for it to be worth running. ``auto`` is not a mode: it picks one of these by measurement
(``gcdtrav.service.backends.precision_choice``). ``gcdtrav.schemas.settings.Precision`` lists the same names as a
literal (the schemas cannot import the service); tests/service/backends/test_modes.py checks they agree.
No torch here: the table is data.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

Runtime = Literal["torch", "onnxruntime"]
Arithmetic = Literal["fp32", "bf16", "int8"]
Need = Literal["native-bf16", "onnxruntime"]
# Without onnxruntime an ort-* mode cannot be built at all; without native bf16 a bf16 mode runs, emulated and
# slow, so only auto leaves it out.
REQUIRED: frozenset[Need] = frozenset({"onnxruntime"})
AUTO = "auto"


@dataclass(frozen=True)
class RuntimeMode:
    name: str
    runtime: Runtime
    trunk: Arithmetic  # the ViT layers the decoder reads
    decoder: Arithmetic  # the decoder's MLPs (its attention and FiLM stay fp32 in the int8 modes)
    needs: frozenset[Need]
    description: str

    @property
    def on_onnxruntime(self) -> bool:
        return self.runtime == "onnxruntime"


MODES: tuple[RuntimeMode, ...] = (
    RuntimeMode("fp32", "torch", "fp32", "fp32", frozenset(), "torch in fp32: the reference"),
    RuntimeMode("bf16", "torch", "bf16", "bf16", frozenset({"native-bf16"}), "torch, ViT and decoder in bfloat16"),
    RuntimeMode(
        "bf16-vit", "torch", "bf16", "fp32", frozenset({"native-bf16"}), "torch, the ViT in bfloat16, the decoder fp32"
    ),
    RuntimeMode("int8", "torch", "int8", "fp32", frozenset(), "torch's dynamic int8 ViT, fp32 decoder"),
    RuntimeMode("ort-fp32", "onnxruntime", "fp32", "fp32", frozenset({"onnxruntime"}), "ONNX Runtime in fp32 (exact)"),
    RuntimeMode(
        "ort-int8-vit",
        "onnxruntime",
        "int8",
        "fp32",
        frozenset({"onnxruntime"}),
        "ONNX Runtime, dynamic int8 ViT, fp32 decoder",
    ),
    RuntimeMode(
        "ort-int8",
        "onnxruntime",
        "int8",
        "int8",
        frozenset({"onnxruntime"}),
        "ONNX Runtime, dynamic int8 ViT and decoder MLPs",
    ),
)
BY_NAME: dict[str, RuntimeMode] = {mode.name: mode for mode in MODES}
NAMES: tuple[str, ...] = (AUTO, *BY_NAME)  # what the precision setting accepts, in this order


def runtime_mode(name: str) -> RuntimeMode:
    """The concrete mode of that name; ValueError (listing the names) for anything else, ``auto`` included."""
    try:
        return BY_NAME[name]
    except KeyError:
        raise ValueError(f"precision must be one of {', '.join(NAMES)}, not '{name}'") from None


def modes_with(has: Callable[[Need], bool]) -> list[str]:
    """The modes whose needs this machine meets, in the table's order."""
    return [mode.name for mode in MODES if all(has(need) for need in mode.needs)]


def missing_requirement(mode: RuntimeMode, has: Callable[[Need], bool]) -> Need | None:
    """What the machine lacks to build the mode at all (None: it can be built)."""
    return next((need for need in sorted(mode.needs & REQUIRED) if not has(need)), None)
