"""Would an ONNX Runtime backend win? The ViT trunk (the part that costs the most) in ORT against torch.

    pip install onnxruntime onnx onnxscript      # not dependencies of gcdtrav: only for this trial
    python -m benchmarks.onnxruntime_trial [--model DIR] [--runs 9]

Exports the trunk the decoder reads (embeddings, pre-norm, layers 0..9, outputs after layers 3, 6, 9) with
torch's TorchScript exporter, runs it in ONNX Runtime's CPU provider in fp32 and with ORT's dynamic int8
quantisation, and times it next to this project's torch trunk in fp32 and bf16, in one process. Parity:
mean per-token cosine similarity and max |difference| of the three activations against torch fp32.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from gcdtrav.service.bench import time_call


def median_ms(fn: Callable[[], object], runs: int) -> float:
    return statistics.median(time_call(fn, runs)[0])  # the benchmark's own timing: one warm-up, then runs


class TrunkForExport(torch.nn.Module):
    def __init__(self, trunk: torch.nn.Module, wanted: list[int]) -> None:
        super().__init__()
        self.trunk, self.wanted = trunk, wanted

    def forward(self, pixels: torch.Tensor) -> tuple[torch.Tensor, ...]:
        t = self.trunk
        hidden = t.pre_layrnorm(t.embeddings(pixels, interpolate_pos_encoding=True))
        kept = []
        for index, layer in enumerate(t.layers):
            hidden = layer(hidden, None)  # transformers' own layer: what ONNX gets
            if index in self.wanted:
                kept.append(hidden)
        return tuple(kept)


def main() -> int:
    import onnxruntime as ort
    from gcdtrav.service.backends.clipseg import ClipSegBackend
    from gcdtrav.service.bench import bench_image
    from onnxruntime.quantization import QuantType, quantize_dynamic

    from tools.random_clipseg import save_random_clipseg

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default=None, help="checkpoint directory [random weights, real architecture]")
    parser.add_argument("--runs", type=int, default=9)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        model = args.model or str(save_random_clipseg(Path(scratch) / "model", preset="rd64-refined"))
        fp32 = ClipSegBackend(model, precision="fp32")
        bf16 = ClipSegBackend(model, precision="bf16")
        pixels = fp32.preprocess(bench_image())
        export = TrunkForExport(fp32._trunk, fp32.extract_layers).eval()
        with torch.inference_mode():
            reference = [a.numpy() for a in export(pixels)]
        plain, quantised = Path(scratch) / "trunk.onnx", Path(scratch) / "trunk-int8.onnx"
        torch.onnx.export(export, (pixels,), str(plain), dynamo=False, opset_version=17, input_names=["pixels"])
        quantize_dynamic(str(plain), str(quantised), weight_type=QuantType.QInt8)

        rows: list[tuple[str, float, float, float]] = []
        with torch.inference_mode():
            for name, backend in (("torch fp32 (this project)", fp32), ("torch bf16 (this project)", bf16)):
                outs = [a.float().numpy() for a in backend.vision_activations(pixels)]
                rows.append(
                    (
                        name,
                        median_ms(lambda b=backend: b.vision_activations(pixels), args.runs),
                        *parity(reference, outs),
                    )
                )
        options = ort.SessionOptions()
        options.intra_op_num_threads = torch.get_num_threads()
        feed = {"pixels": pixels.numpy()}
        for name, path in (("ONNX Runtime fp32", plain), ("ONNX Runtime int8 (dynamic)", quantised)):
            session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
            outs = session.run(None, feed)
            rows.append((name, median_ms(lambda s=session: s.run(None, feed), args.runs), *parity(reference, outs)))
    print(f"ViT trunk (10 layers, 352x352), {torch.get_num_threads()} threads, onnxruntime {ort.__version__}")
    print("| runtime | median ms | activation cosine (min of 3) | max abs diff |")
    print("|---|---:|---:|---:|")
    for name, ms, cosine, diff in rows:
        print(f"| {name} | {ms:.1f} | {cosine:.6f} | {diff:.3g} |")
    return 0


def parity(reference: list[np.ndarray], candidate: list[np.ndarray]) -> tuple[float, float]:
    cosines, diffs = [], []
    for ref, cand in zip(reference, candidate, strict=True):
        r, c = ref.reshape(-1, ref.shape[-1]), np.asarray(cand, np.float32).reshape(-1, ref.shape[-1])
        cosines.append(float(np.mean((r * c).sum(1) / (np.linalg.norm(r, axis=1) * np.linalg.norm(c, axis=1)))))
        diffs.append(float(np.abs(r - c).max()))
    return min(cosines), max(diffs)


if __name__ == "__main__":
    sys.exit(main())
