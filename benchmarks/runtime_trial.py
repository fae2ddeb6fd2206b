"""Which runtime runs the ViT trunk fastest here? The candidates side by side, interleaved in one process.

    python -m benchmarks.runtime_trial [--model DIR] [--rounds 9]
    pip install torchao      # optional: adds torch's x86 int8 path (PT2E + X86InductorQuantizer + inductor)

The trunk (embeddings, pre-norm, layers 0..9; the three activations the decoder reads) is the part that
costs the most. Rows: this project's torch fp32 trunk and its ONNX Runtime exports (``ort-fp32``,
``ort-int8``: built by the same code ``precision: auto`` uses), and, when torchao imports, torchao's PT2E
int8 (dynamic and static, calibrated on four random inputs) compiled by inductor with freezing. Each round
runs every row once in turn, so the machine's drift hits all rows alike; the first round is a warm-up.
Parity: the smallest per-token cosine similarity of the three activations against torch fp32.
Without ``--model``: random weights of the real rd64-refined architecture.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path

import torch
from gcdtrav.service.backends.clipseg import ClipSegBackend
from gcdtrav.service.backends.precision_choice import synthetic_image
from gcdtrav.service.backends.timing import interleaved_ms
from gcdtrav.service.commands.bench import machine_header
from gcdtrav.service.commands.doctor import machine_info

from tools.random_clipseg import checkpoint_or_random

Trunk = Callable[[torch.Tensor], Sequence[torch.Tensor]]
REFERENCE = "torch fp32 (fp32)"
PROJECT_TRUNKS = {
    REFERENCE: "fp32",
    "ONNX Runtime fp32 (ort-fp32)": "ort-fp32",
    "ONNX Runtime dynamic int8 (ort-int8)": "ort-int8",
}


def torchao_trunks(backend: ClipSegBackend, pixels: torch.Tensor) -> dict[str, Trunk]:
    """torchao's PT2E int8 trunk, dynamic and static, compiled; {} (with a line saying why) without torchao."""
    try:
        import torchao.quantization.pt2e.quantizer.x86_inductor_quantizer as x86
        from torchao.quantization.pt2e.quantize_pt2e import convert_pt2e, prepare_pt2e
    except ImportError as err:
        print(f"torchao rows skipped: {err} (pip install torchao)", file=sys.stderr)
        return {}
    import torch._inductor.config as inductor
    from gcdtrav.service.backends.onnx_graphs import TrunkGraph

    inductor.freezing = True  # constant weights: oneDNN's packed int8 linears
    graph = TrunkGraph(backend.model.clip.vision_model, backend.extract_layers, pixels.shape[-1]).eval()
    generator = torch.Generator().manual_seed(0)
    calibration = [torch.randn(pixels.shape, generator=generator) for _ in range(4)]
    trunks: dict[str, Trunk] = {}
    for dynamic in (True, False):
        quantizer = x86.X86InductorQuantizer()
        quantizer.set_global(x86.get_default_x86_inductor_quantization_config(is_dynamic=dynamic))
        prepared = prepare_pt2e(torch.export.export(graph, (pixels,)).module(), quantizer)
        for sample in calibration:
            prepared(sample)
        compiled = torch.compile(convert_pt2e(prepared))
        compiled(pixels)  # compiles here, not in the first timed round
        trunks[f"torchao PT2E int8 {'dynamic' if dynamic else 'static'} (inductor)"] = compiled
    return trunks


def min_cosine(reference: Sequence[torch.Tensor], candidate: Sequence[torch.Tensor]) -> float:
    worst = 1.0
    for ref, cand in zip(reference, candidate, strict=True):
        r = ref.float().reshape(-1, ref.shape[-1])
        c = cand.float().reshape(-1, ref.shape[-1])
        worst = min(worst, float(torch.nn.functional.cosine_similarity(r, c, dim=1).min()))
    return worst


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", type=Path, default=None, help="checkpoint directory [random, real architecture]")
    parser.add_argument("--rounds", type=int, default=9)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as scratch, torch.inference_mode(False), torch.no_grad():
        model = checkpoint_or_random(args.model, Path(scratch))
        backend = ClipSegBackend(str(model), precision="fp32", keep_reference=True, cache_dir=Path(scratch) / "cache")
        pixels = backend.preprocess(synthetic_image())
        trunks: dict[str, Trunk] = {
            name: backend.compute_for(mode).activations for name, mode in PROJECT_TRUNKS.items()
        }
        trunks.update(torchao_trunks(backend, pixels))
        reference = trunks[REFERENCE](pixels)
        cosines = {name: min_cosine(reference, trunk(pixels)) for name, trunk in trunks.items()}
        times = interleaved_ms({name: partial(trunk, pixels) for name, trunk in trunks.items()}, args.rounds)
    print(machine_header(machine_info()))
    print(
        f"ViT trunk ({max(backend.extract_layers) + 1} layers, {pixels.shape[-1]}x{pixels.shape[-1]}), "
        f"{args.rounds} interleaved rounds"
    )
    print("| trunk | median ms | × fp32 | min activation cosine vs fp32 |")
    print("|---|---:|---:|---:|")
    first = statistics.median(times[REFERENCE])
    for name, values in times.items():
        median = statistics.median(values)
        print(f"| {name} | {median:.1f} | {first / median:.2f} | {cosines[name]:.5f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
