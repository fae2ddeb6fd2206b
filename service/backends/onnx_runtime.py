"""The fast path on ONNX Runtime: exported once per checkpoint and CPU, cached on disk, run by OrtCompute.

Why ONNX Runtime: on AVX2-only x86 (no AVX-512, no AMX) its dynamic int8 matrix products run the ViT
trunk at about twice torch's fp32 speed, and its fp32 decoder beats torch's by about a fifth, with the
int8 trunk well inside the parity gate (benchmarks/README.md, "AVX2-only x86"). On an AVX512-BF16 EPYC it
is auto's pick too: 109 ms a frame against torch bf16's 196 (benchmarks/README.md, issue 60).

The exported models live in ``<cache>/onnx/<key>/``; the key hashes the checkpoint's files, the input
size, the layers read, the versions of torch, onnx and onnxruntime, and the CPU's features, so a new
checkpoint, an upgrade or a different CPU never reuses a stale export. A directory is built under a
temporary name and renamed into place when complete, so a crash never leaves a half-written model
behind; ``manifest.json`` records each file's SHA-256, and a model that fails the check or fails to load
is rebuilt with a warning.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import os
import shutil
import tempfile
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from gcdtrav.service.backends.cpus import cpu_features
from gcdtrav.service.backends.decoder import blocks_to_image
from gcdtrav.service.backends.expected_warnings import expected_torch_warnings

log = logging.getLogger(__name__)

# ONNX Runtime's POSIX telemetry writes a device id and an event queue under ~/.cache/Microsoft/DeveloperTools/
# when it is first imported, unless this is set before (it is read once, at that import). gcdtrav writes
# only to its state and cache directories, and a robot's box sends nothing it was not asked to: off, unless
# the user set it. Every import of onnxruntime in gcdtrav goes through this module.
os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")

EXPORT_FORMAT = 6  # bump when the exported graphs change
TRUNK, TRUNK_INT8, DECODER, DECODER_INT8 = "trunk.onnx", "trunk-int8.onnx", "decoder.onnx", "decoder-int8.onnx"
REDUCTION = "reduction.onnx"
EXPORTED_FILES = (TRUNK, TRUNK_INT8, REDUCTION, DECODER, DECODER_INT8)
REDUCTION_INPUTS = ["first", "second", "third"]  # the trunk's outputs, in the order of the layers read
REDUCED = ["reduced0", "reduced1", "reduced2"]  # in the decoder's order: the last layer read first
DECODER_INPUTS = [*REDUCED, "conditional"]
WEIGHT_FILES = ("*.safetensors", "*.bin", "config.json")
# The decoder in ONNX Runtime: one one-thread session per thread, each running its share of the chunks of
# concepts side by side, rather than one session spreading each of the decoder's many small nodes over the
# threads and waiting for the slowest at every node. Measured on a 2-core AVX512 EPYC, 13 concepts, the int8
# decoder a frame: one 2-thread session, 4 concepts a run, 45.4 ms; two 1-thread sessions side by side, 1, 2
# or 3 concepts a run, 28.6, 28.6, 29.3 ms; one 1-thread session alone, 1, 2, 3, 4, 8 concepts a run: 52.5,
# 52.9, 54.1, 56.7, 67.4 ms (the MLP's concepts x tokens x 2048 intermediate should stay in cache).
ORT_DECODER_CHUNK = 2
# At most this many decoder sessions (a many-core box gives each threads // sessions threads): every session
# keeps its own memory arena, about 22 MB more each for rd64-refined's int8 decoder in chunks of 2.
DECODER_SESSIONS_MAX = 4


class ExportError(RuntimeError):
    """The model could not be exported for ONNX Runtime (the torch modes still work)."""


def onnx_runtime_available() -> bool:
    try:
        import onnx  # noqa: F401
        import onnxruntime  # noqa: F401
    except ImportError:
        return False
    return True


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def checkpoint_files(checkpoint: Path) -> list[Path]:
    return sorted({path for pattern in WEIGHT_FILES for path in checkpoint.glob(pattern) if path.is_file()})


def checkpoint_digests(checkpoint: Path) -> dict[str, str]:
    """SHA-256 of each of the checkpoint's weight files, by name. The export key and auto's measurement key
    both need it, once per mode, and rd64-refined's 600 MB take about a second to hash: each file is hashed
    once per process while its size and modification time stay the same."""
    digests = {}
    for path in checkpoint_files(checkpoint):
        stat = path.stat()
        digests[path.name] = _sha256_while_unchanged(path.resolve(), stat.st_size, stat.st_mtime_ns)
    return digests


def model_fingerprint(checkpoint: Path | None) -> str:
    """16 hex digits that differ between checkpoints: a hash over the config and the weight files' hashes.
    Instances compare it (service/runtime/fleet/fleet_models.py); "" when the checkpoint's files are not found."""
    digests = checkpoint_digests(checkpoint) if checkpoint is not None else {}
    return hashlib.sha256(json.dumps(digests, sort_keys=True).encode()).hexdigest()[:16] if digests else ""


@functools.lru_cache(maxsize=32)
def _sha256_while_unchanged(path: Path, size: int, mtime_ns: int) -> str:
    return file_sha256(path)


def export_key(checkpoint: Path, input_size: int, extract_layers: Sequence[int]) -> dict[str, Any]:
    """Everything an exported model depends on; its hash names the cache directory."""
    import onnx
    import onnxruntime

    return {
        "format": EXPORT_FORMAT,
        "checkpoint": checkpoint_digests(checkpoint),
        "input_size": input_size,
        "extract_layers": list(extract_layers),
        "torch": torch.__version__,
        "onnx": onnx.__version__,
        "onnxruntime": onnxruntime.__version__,
        "cpu": cpu_features(),
    }


def key_digest(key: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:24]


@dataclass(frozen=True)
class ExportedModel:
    """A complete, verified export: the directory and the key it was built for."""

    directory: Path
    key: dict[str, Any]

    def path(self, name: str) -> Path:
        return self.directory / name


def _verified(directory: Path, key: dict[str, Any]) -> ExportedModel | None:
    """The export in ``directory`` if its manifest matches the key and every file its hash; None if absent."""
    manifest_path = directory / "manifest.json"
    if not directory.exists():
        return None
    try:
        manifest = json.loads(manifest_path.read_text("utf-8"))
        if manifest["key"] != key:
            raise ValueError("it was built for another checkpoint, version or CPU")
        if set(manifest["files"]) != set(EXPORTED_FILES):
            raise ValueError(f"it holds {sorted(manifest['files'])}, not {list(EXPORTED_FILES)}")
        for name, expected in manifest["files"].items():
            if file_sha256(directory / name) != expected:
                raise ValueError(f"{name} does not match its recorded hash")
    except (OSError, ValueError, KeyError, TypeError) as err:
        log.warning("the cached ONNX export in %s is unusable (%s); rebuilding it", directory, err)
        shutil.rmtree(directory, ignore_errors=True)
        return None
    return ExportedModel(directory, key)


def exported_model(
    vision: Any, decoder: Any, extract_layers: Sequence[int], checkpoint: Path, input_size: int, cache_dir: Path
) -> ExportedModel:
    """The cached export for this checkpoint and machine, built (export, int8 quantisation) if missing."""
    key = export_key(checkpoint, input_size, extract_layers)
    final = cache_dir / "onnx" / key_digest(key)
    found = _verified(final, key)
    if found is not None:
        return found
    final.parent.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    log.info("exporting the model for ONNX Runtime into %s (once per checkpoint and CPU) ...", final)
    building = Path(tempfile.mkdtemp(prefix=f".{final.name}.", dir=final.parent))
    try:
        _export(vision, decoder, list(extract_layers), input_size, building)
        files = {name: file_sha256(building / name) for name in EXPORTED_FILES}
        (building / "manifest.json").write_text(json.dumps({"key": key, "files": files}, indent=1), "utf-8")
        for path in building.iterdir():
            with path.open("rb") as handle:
                os.fsync(handle.fileno())
        try:
            building.rename(final)
        except OSError:  # another process finished the same export first: use its copy
            shutil.rmtree(building, ignore_errors=True)
    except Exception as err:
        shutil.rmtree(building, ignore_errors=True)
        raise ExportError(f"cannot export the model for ONNX Runtime: {type(err).__name__}: {err}") from err
    log.info("ONNX export ready in %.1f s", time.monotonic() - started)
    found = _verified(final, key)
    if found is None:
        raise ExportError(f"the ONNX export in {final} failed its check right after it was written")
    return found


def _export(vision: Any, decoder: Any, extract_layers: list[int], input_size: int, into: Path) -> None:
    import onnx
    from gcdtrav.service.backends.onnx_graphs import DecoderGraph, ReductionGraph, TrunkGraph

    trunk, reduction = TrunkGraph(vision, extract_layers, input_size).eval(), ReductionGraph(decoder).eval()
    pixels = torch.zeros(1, 3, input_size, input_size)
    with torch.no_grad(), expected_torch_warnings(tracing=True):  # the export is checked against torch after
        activations = trunk(pixels)
        reduced = reduction(*activations)
        conditional = torch.zeros(2, decoder.film_mul.in_features)
        torch.onnx.export(trunk, (pixels,), str(into / TRUNK), dynamo=False, opset_version=17, input_names=["pixels"])
        torch.onnx.export(
            reduction,
            tuple(activations),
            str(into / REDUCTION),
            dynamo=False,
            opset_version=17,
            input_names=REDUCTION_INPUTS,
            output_names=REDUCED,
        )
        torch.onnx.export(
            DecoderGraph(decoder).eval(),
            (*reduced, conditional),
            str(into / DECODER),
            dynamo=False,
            opset_version=17,
            input_names=DECODER_INPUTS,
            output_names=["logits"],
            dynamic_axes={"conditional": {0: "concepts"}, "logits": {0: "concepts"}},
        )
    # Dynamic int8 (weights per tensor, activations per call) on matrix products only: the patch
    # embedding's convolution is faster in fp32 (ConvInteger measured 13 ms against about 3 ms). In the
    # decoder only the MLPs, which are three quarters of its work; attention stays fp32.
    decoder_mlps = [node.name for node in onnx.load(str(into / DECODER)).graph.node if "/mlp/fc" in node.name]
    _quantise(into / TRUNK, into / TRUNK_INT8, None)
    _quantise(into / DECODER, into / DECODER_INT8, decoder_mlps)


def _quantise(source: Path, target: Path, nodes: list[str] | None) -> None:
    import onnx
    from onnxruntime.quantization import QuantType, quantize_dynamic

    root = logging.getLogger()
    level, root.level = root.level, logging.ERROR  # the quantiser logs every tensor on the root logger
    try:
        quantize_dynamic(
            str(source),
            str(target),
            weight_type=QuantType.QInt8,
            op_types_to_quantize=["MatMul", "Gemm"],
            nodes_to_quantize=nodes,
            extra_options={"DefaultTensorType": onnx.TensorProto.FLOAT},
        )
    finally:
        root.level = level


def session_options(threads: int) -> Any:
    """ONNX Runtime's options for a gcdtrav session of ``threads`` threads."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    # Each session has its own thread pool; spinning threads of the idle one would take the cores
    # from the running one (measured on a 2-core EPYC: ort-int8 597 ms per frame spinning, 453 not).
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return options


# ONNX Runtime fuses an Add followed by a LayerNormalization into its SkipLayerNormalization, whose CPU kernel is
# slower than the two it replaces: measured on a 2-core AVX512 EPYC, (1, 485, 768), 1.47 ms against 0.23 on one
# thread, 0.79 against 0.16 on two. It fused the embeddings' Add into pre_layrnorm in export format 5 (the
# int8 trunk 75.6 -> 74.5 ms without it, one run); format 6 leaves it nothing to fuse, and an ONNX Runtime that
# fuses more (the residual Adds that feed a second node) must not bring the slower kernel back.
DISABLED_OPTIMIZERS = ["SkipLayerNormFusion"]


def inference_session(path: Path, threads: int) -> Any:
    """An ONNX Runtime CPU session of gcdtrav's options for the exported model at ``path``."""
    import onnxruntime as ort

    options, providers = session_options(threads), ["CPUExecutionProvider"]
    return ort.InferenceSession(str(path), options, providers=providers, disabled_optimizers=DISABLED_OPTIMIZERS)


class OrtCompute:
    """The trunk and the reductions as one ONNX Runtime session each, the decoder as one session per thread
    (up to ``DECODER_SESSIONS_MAX``), side by side; the same calls as the torch path."""

    def __init__(self, model: ExportedModel, int8_trunk: bool, int8_decoder: bool, threads: int) -> None:
        threads = max(1, threads)
        try:
            self.trunk = inference_session(model.path(TRUNK_INT8 if int8_trunk else TRUNK), threads)
            self.reduction = inference_session(model.path(REDUCTION), threads)
            decoder = model.path(DECODER_INT8 if int8_decoder else DECODER)
            sessions = min(threads, DECODER_SESSIONS_MAX)
            self.decoders = [inference_session(decoder, threads // sessions) for _ in range(sessions)]
        except Exception as err:  # onnxruntime raises its own exception types
            raise ExportError(f"ONNX Runtime cannot load the export in {model.directory}: {err}") from err
        self.trunk_input = self.trunk.get_inputs()[0].name
        # The calling thread runs the first share; these run the others (their threads idle between frames).
        helpers = len(self.decoders) - 1
        self._helpers = ThreadPoolExecutor(helpers, "gcdtrav-decoder") if helpers else None

    def activations(self, pixel_values: torch.Tensor) -> list[torch.Tensor]:
        expected = self.trunk.get_inputs()[0].shape
        if list(pixel_values.shape) != expected:
            raise ValueError(f"this ONNX export takes pixels of shape {expected}, not {list(pixel_values.shape)}")
        outputs = self.trunk.run(None, {self.trunk_input: pixel_values.float().numpy()})
        return [torch.from_numpy(np.asarray(output)) for output in outputs]

    def decode(self, activations: Sequence[torch.Tensor], conditional: torch.Tensor) -> torch.Tensor:
        """Chunks of concepts, shared round-robin among the decoder sessions, which run side by side."""
        trunk_outputs = dict(zip(REDUCTION_INPUTS, [a.float().numpy() for a in activations], strict=True))
        reduced = dict(zip(REDUCED, self.reduction.run(None, trunk_outputs), strict=True))
        concepts = conditional.float().numpy()
        starts = range(0, concepts.shape[0], ORT_DECODER_CHUNK)
        sessions = len(self.decoders)

        def share(index: int) -> list[Any]:
            run = self.decoders[index].run
            return [
                run(None, {**reduced, "conditional": concepts[start : start + ORT_DECODER_CHUNK]})[0]
                for start in starts[index::sessions]
            ]

        others = [self._helpers.submit(share, index) for index in range(1, sessions)] if self._helpers else []
        shares = [share(0), *[other.result() for other in others]]
        return concept_logits([shares[position % sessions][position // sessions] for position in range(len(starts))])


def concept_logits(chunks: Sequence[Any]) -> torch.Tensor:
    """The decoder runs' outputs, in concept order, as (n, S, S) logits: nested blocks put in image order once."""
    logits = torch.from_numpy(np.concatenate(chunks))
    return logits if logits.dim() == 3 else blocks_to_image(logits).squeeze(1)
