"""CLIPSeg (Lüddecke & Ecker, CVPR 2022) as a segmentation backend, with the work per frame cut to what
the decoder needs.

transformers' ``CLIPSegForImageSegmentation.forward`` takes one (image, prompt) pair per batch row, so an
anchor set of n concepts runs the ViT n times on the same image and all 12 of its layers. Here:
  * the vision encoder runs once per image and stops after the last layer the decoder reads
    (``config.extract_layers``, layers 3, 6 and 9 of 12 in rd64-refined, so 10 layers run);
  * the decoder runs batched over the n concepts (``decoder.py``), its reductions on the one image's
    tokens, broadcast at the FiLM conditioning;
  * activations are fused into the linear layers where oneDNN can (``onednn.py``);
  * the text-conditional embeddings are computed once per anchor set and cached.
The results match transformers' own forward (see tests/service/backends/test_backend_clipseg.py).
"""

from __future__ import annotations

import copy
import ctypes
import ctypes.util
import gc
import json
import logging
import mmap
import sys
import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeAlias

import cv2
import numpy as np
import torch
from gcdtrav.schemas.paths import default_cache_dir, expanded
from gcdtrav.service.backends.base import BackendDescription, ModelUnavailableError
from gcdtrav.service.backends.decoder import DECODER_CHUNK, FastDecoder
from gcdtrav.service.backends.expected_warnings import expected_torch_warnings
from gcdtrav.service.backends.hub import cached_in_hub_cache, hub_offline
from gcdtrav.service.backends.machine import available_precisions, machine_has
from gcdtrav.service.backends.modes import AUTO, RuntimeMode, missing_requirement, runtime_mode
from gcdtrav.service.backends.onednn import QuickGeluMLP, clip_encoder_layer, fused_mlp_pays
from gcdtrav.service.backends.onnx_runtime import ExportError, OrtCompute, exported_model, model_fingerprint
from numpy.typing import NDArray

log = logging.getLogger(__name__)

_PAGE = mmap.PAGESIZE
_MADV_DONTNEED = 4  # Linux
_LIBC = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True) if sys.platform == "linux" else None

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
CLIPSEG_INPUT_SIZE = 352
HOW_TO_PROVIDE_WEIGHTS = (
    "to provide the weights, on a machine with internet run "
    "`hf download CIDAS/clipseg-rd64-refined --local-dir clipseg-rd64-refined`, "
    "copy that directory to this machine, then pass `--model ./clipseg-rd64-refined` "
    "or set GCDTRAV_MODEL=./clipseg-rd64-refined"
)


@dataclass(frozen=True)
class Preprocessing:
    """How an image becomes pixel values: a square resize (CLIPSeg ignores aspect) and normalisation."""

    size: int = CLIPSEG_INPUT_SIZE
    mean: tuple[float, float, float] = IMAGENET_MEAN
    std: tuple[float, float, float] = IMAGENET_STD

    @classmethod
    def from_config_file(cls, path: Path | None) -> Preprocessing:
        if path is None or not path.is_file():
            return cls()
        raw: dict[str, Any] = json.loads(path.read_text("utf-8"))
        size = raw.get("size", CLIPSEG_INPUT_SIZE)
        if isinstance(size, dict):
            size = size.get("height") or size.get("shortest_edge") or CLIPSEG_INPUT_SIZE
        return cls(
            size=int(size),
            mean=_triple(raw.get("image_mean", IMAGENET_MEAN)),
            std=_triple(raw.get("image_std", IMAGENET_STD)),
        )

    def __call__(self, image_rgb: NDArray[np.uint8]) -> torch.Tensor:
        """(1, 3, size, size) float32: (pixel / 255 - mean) / std, as one multiply and one subtract into the
        channel-first result (five passes and four temporaries before: 1.0 ms, now 0.25 for 640x480)."""
        resized = cv2.resize(image_rgb, (self.size, self.size), interpolation=cv2.INTER_LINEAR)
        mean, std = np.asarray(self.mean, np.float32), np.asarray(self.std, np.float32)
        pixels = np.empty((3, self.size, self.size), np.float32)
        np.multiply(resized.transpose(2, 0, 1), (np.float32(1 / 255.0) / std)[:, None, None], out=pixels)
        np.subtract(pixels, (mean / std)[:, None, None], out=pixels)
        return torch.from_numpy(pixels)[None]


def check_precision(requested: str) -> str:
    """A concrete mode (not auto) this machine can build; the error says what is missing."""
    missing = missing_requirement(runtime_mode(requested), machine_has)
    if missing == "onnxruntime":
        raise ModelUnavailableError(
            f"precision '{requested}' needs ONNX Runtime: pip install onnxruntime onnx (in gcdtrav[service])"
        )
    return requested


class VisionTrunk(torch.nn.Module):
    """The part of the ViT the decoder reads: embeddings, pre-norm, layers 0..last_layer.

    fp32 shares the model's modules; bf16 and int8 (dynamic quantisation of the linear layers) work on a
    copy, so the model itself stays the fp32 reference.
    """

    def __init__(
        self,
        embeddings: torch.nn.Module,
        pre_layrnorm: torch.nn.Module,
        layers: torch.nn.ModuleList,
        dtype: torch.dtype,
    ) -> None:
        super().__init__()
        self.embeddings, self.pre_layrnorm, self.layers, self.dtype = embeddings, pre_layrnorm, layers, dtype
        self.fused_mlps: list[QuickGeluMLP | None] = [None] * len(layers)

    @classmethod
    def build(cls, vision: Any, last_layer: int, arithmetic: str, tokens: int) -> VisionTrunk:
        """``tokens``: how many the input size gives (patches + class token), for timing the fused MLP."""
        layers = torch.nn.ModuleList(list(vision.encoder.layers)[: last_layer + 1])
        trunk = cls(vision.embeddings, vision.pre_layrnorm, layers, torch.float32)
        if arithmetic == "bf16":
            # Copied one module at a time: never a second fp32 copy of the whole trunk in memory.
            copies = [copy.deepcopy(module).to(torch.bfloat16) for module in (vision.embeddings, vision.pre_layrnorm)]
            bf16_layers = torch.nn.ModuleList(copy.deepcopy(layer).to(torch.bfloat16) for layer in layers)
            trunk = cls(copies[0], copies[1], bf16_layers, torch.bfloat16)
        elif arithmetic == "int8":
            with expected_torch_warnings():  # torch deprecates what int8 uses: said once in the docs, not per run
                quantized = torch.ao.quantization.quantize_dynamic(
                    copy.deepcopy(trunk), {torch.nn.Linear}, dtype=torch.qint8
                )
            assert isinstance(quantized, VisionTrunk)
            trunk = quantized
        # Quick-GELU as a fused oneDNN post-op where it applies (not on int8's quantised linears) and is
        # faster on this CPU.
        fused = [QuickGeluMLP.build(layer.layer_norm2, layer.mlp, trunk.dtype) for layer in trunk.layers]
        first = fused[0] if fused else None
        if first is not None and fused_mlp_pays(trunk.layers[0], first, tokens):
            trunk.fused_mlps = fused
        return trunk

    def run(self, pixel_values: torch.Tensor, wanted: set[int]) -> list[torch.Tensor]:
        """Hidden states after each layer in ``wanted``; layers after the last one kept are never run."""
        hidden = self.pre_layrnorm(self.embeddings(pixel_values.to(self.dtype), interpolate_pos_encoding=True))
        kept = []
        for index, layer in enumerate(self.layers):
            hidden = clip_encoder_layer(layer, hidden, self.fused_mlps[index])
            if index in wanted:
                kept.append(hidden)
        return kept


class TorchCompute:
    """Trunk and decoder in torch, in a torch mode's arithmetic (modes.py)."""

    def __init__(self, model: Any, extract_layers: list[int], mode: RuntimeMode, tokens: int) -> None:
        self.extract_layers = extract_layers
        self.trunk = VisionTrunk.build(model.clip.vision_model, max(extract_layers), mode.trunk, tokens)
        decoder, self.decoder_dtype = model.decoder, torch.float32
        if mode.decoder == "bf16":  # the decoder's MLPs, run once per anchor, cost as much as the ViT
            decoder, self.decoder_dtype = copy.deepcopy(decoder).to(torch.bfloat16), torch.bfloat16
        self.decoder = FastDecoder(decoder, tokens)

    def activations(self, pixel_values: torch.Tensor) -> list[torch.Tensor]:
        kept = self.trunk.run(pixel_values, set(self.extract_layers))
        return [hidden.to(self.decoder_dtype) for hidden in kept]

    def decode(self, activations: Sequence[torch.Tensor], conditional: torch.Tensor) -> torch.Tensor:
        """Chunks keep the MLP's (concepts x tokens x 2048) intermediate small enough to stay in cache."""
        conditional = conditional.to(self.decoder_dtype)
        activations = [a.to(self.decoder_dtype) for a in activations]
        chunks = [
            self.decoder(activations, conditional[k : k + DECODER_CHUNK])
            for k in range(0, conditional.shape[0], DECODER_CHUNK)
        ]
        return torch.cat(chunks).float()


Compute: TypeAlias = TorchCompute | OrtCompute


def _triple(values: Any) -> tuple[float, float, float]:
    first, second, third = (float(v) for v in values)
    return first, second, third


def release_pages(tensor: torch.Tensor) -> None:
    """Give the memory pages that lie wholly inside a tensor about to be dropped back to the OS now.

    transformers memory-maps the checkpoint, and every weight keeps the whole mapping alive: the pages of
    fp32 layers read once (to make the bf16 copy) would stay resident for the process's life. Pages
    shared with a neighbouring tensor are left alone; on a private file mapping a released page would
    read back from the file, on anonymous memory as zeros, but the tensor is dropped right after.
    """
    storage = tensor.untyped_storage()
    start, end = storage.data_ptr(), storage.data_ptr() + storage.nbytes()
    first, last = -(-start // _PAGE) * _PAGE, end // _PAGE * _PAGE
    if _LIBC is not None and last > first:
        _LIBC.madvise(ctypes.c_void_p(first), ctypes.c_size_t(last - first), _MADV_DONTNEED)


def _locate(model: str, filename: str) -> Path | None:
    """A file of the checkpoint: in the directory, or in the hub cache after from_pretrained fetched it."""
    if Path(model).is_dir():
        candidate = Path(model) / filename
        return candidate if candidate.is_file() else None
    try:
        from transformers.utils import cached_file

        found = cached_file(model, filename, _raise_exceptions_for_missing_entries=False, local_files_only=True)
    except (OSError, ValueError):
        return None
    return Path(found) if found else None


def hub_load_options(model: str) -> dict[str, Any]:
    """``from_pretrained``'s options for a hub id: the local cache only when the hub cannot be reached (then a
    model not in the cache fails now, not after the hub's retries)."""
    why_offline = hub_offline()
    if why_offline is None:
        return {}
    if not cached_in_hub_cache(model):
        raise ModelUnavailableError(
            f"'{model}' is not a local directory, the Hugging Face hub cannot be used ({why_offline}) and the "
            f"model is not in the hub's local cache; {HOW_TO_PROVIDE_WEIGHTS}"
        )
    log.info("the Hugging Face hub cannot be used (%s): loading '%s' from its local cache", why_offline, model)
    return {"local_files_only": True}


@dataclass(frozen=True)
class RunningMode:
    """The compute frames run with, its mode and why: swapped as one reference, between frames."""

    compute: Compute
    precision: str
    reason: str


class ClipSegBackend:
    """CLIPSeg logits for every concept of an anchor set, one ViT pass per image."""

    def __init__(
        self,
        model: str,
        device: str = "cpu",
        precision: str = "fp32",
        prepared_cache_size: int = 4,
        keep_reference: bool = False,
        cache_dir: Path | None = None,
        measure_now: bool = True,
    ) -> None:
        """``keep_reference``: keep transformers' complete fp32 model for ``naive_logits`` (benchmark, tests).

        Without it, the vision layers the chosen mode does not use are released: the fp32 ViT when the
        trunk is a bf16, int8 or ONNX Runtime copy (about 340 MB for rd64-refined), the layers after the
        last one the decoder reads otherwise. ``cache_dir`` keeps the ONNX exports and the measurements of
        ``precision='auto'`` [$XDG_CACHE_HOME/gcdtrav]. ``measure_now`` False: with auto and no measurement
        cached for this machine, run fp32 and leave ``needs_measurement`` set for the caller to measure (in
        the background: ``precision_choice.measure_then_switch``).
        """
        from transformers import CLIPSegForImageSegmentation, CLIPTokenizer

        self.model_id = model
        self.keeps_reference = keep_reference
        self.device = torch.device(device)
        self.cache_dir = expanded(cache_dir) if cache_dir is not None else default_cache_dir()
        if precision != AUTO:
            check_precision(precision)
        if model.startswith(("/", ".", "~")) and not Path(model).expanduser().is_dir():
            raise ModelUnavailableError(f"model directory '{model}' does not exist; {HOW_TO_PROVIDE_WEIGHTS}")
        model = str(Path(model).expanduser()) if model.startswith("~") else model
        options = {} if Path(model).is_dir() else hub_load_options(model)
        try:
            self.model = CLIPSegForImageSegmentation.from_pretrained(model, **options).eval().to(self.device)
            self.tokenizer = CLIPTokenizer.from_pretrained(model, **options)
        except (OSError, ValueError) as err:
            reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise ModelUnavailableError(
                f"cannot load the CLIPSeg model '{model}' ({reason[:200]}); {HOW_TO_PROVIDE_WEIGHTS}"
            ) from None
        config_file = _locate(model, "config.json")
        self.checkpoint_dir = config_file.parent if config_file is not None else None
        self.fingerprint = model_fingerprint(self.checkpoint_dir)  # once: the weights do not change under us
        self.preprocess = Preprocessing.from_config_file(_locate(model, "preprocessor_config.json"))
        self.extract_layers = list(self.model.config.extract_layers)
        self._prepared: OrderedDict[tuple[str, ...], torch.Tensor] = OrderedDict()
        self._prepared_cache_size = prepared_cache_size
        self._prepare_lock = threading.Lock()  # the anchor switch and a background measurement both prepare
        self._frame_lock = threading.Lock()  # held for a frame: a mode switch waits for the frame in flight
        self.measuring = False  # a background measurement of the modes is running (status reports it)
        self.needs_measurement = False
        precision, reason = self._resolve(precision, measure_now)
        self._running = RunningMode(self.compute_for(precision), precision, reason)
        if not keep_reference:
            self._release_unused_vision_layers()

    def _resolve(self, precision: str, measure_now: bool) -> tuple[str, str]:
        """The concrete mode to start with, and why."""
        if precision != AUTO:
            return precision, f"asked for {precision}"
        from gcdtrav.service.backends import precision_choice

        modes = available_precisions()
        choice = precision_choice.cached_choice(self, modes)
        if choice is None and measure_now:
            choice = precision_choice.measure_and_store(self, modes)
        if choice is None:
            self.needs_measurement = True
            return "fp32", "auto: fp32 until the modes are measured on this machine (measuring in the background)"
        return choice.mode, choice.reason

    def compute_for(self, precision: str) -> Compute:
        """The trunk and decoder of a concrete mode; ONNX Runtime's are exported on first use and cached."""
        mode = runtime_mode(check_precision(precision))
        if not mode.on_onnxruntime:
            return TorchCompute(self.model, self.extract_layers, mode, self.vision_tokens)
        if self.checkpoint_dir is None:
            raise ExportError(f"cannot find the files of checkpoint '{self.model_id}' to key the ONNX export")
        exported = exported_model(
            self.model.clip.vision_model,
            self.model.decoder,
            self.extract_layers,
            self.checkpoint_dir,
            self.preprocess.size,
            self.cache_dir,
        )
        return OrtCompute(exported, mode.trunk == "int8", mode.decoder == "int8", threads=torch.get_num_threads())

    @property
    def vision_tokens(self) -> int:
        """Tokens the ViT sees at this input size: one per patch, plus the class token."""
        return (self.preprocess.size // int(self.model.config.vision_config.patch_size)) ** 2 + 1

    @property
    def compute(self) -> Compute:
        return self._running.compute

    @property
    def precision(self) -> str:
        return self._running.precision

    @property
    def precision_reason(self) -> str:
        return self._running.reason

    def describe(self) -> BackendDescription:
        running = self._running  # one read: precision and reason of the same mode
        return BackendDescription(
            model_id=self.model_id,
            input_size=(self.preprocess.size, self.preprocess.size),
            precision=running.precision,
            precision_reason=running.reason,
            measuring=self.measuring,
            needs_measurement=self.needs_measurement,
            fingerprint=self.fingerprint,
        )

    def use_compute(self, compute: Compute, precision: str, reason: str | None = None) -> None:
        """Run with another mode's compute from the next frame on (one reference swap)."""
        self._running = RunningMode(compute, precision, self.precision_reason if reason is None else reason)

    def switch_to(self, compute: Compute, precision: str, reason: str) -> None:
        """Swap the mode between frames (waits for the frame in flight), then give back the vision layers
        the new mode does not use."""
        with self._frame_lock:
            self.use_compute(compute, precision, reason)
            if not self.keeps_reference:
                self._release_unused_vision_layers()

    def _release_unused_vision_layers(self) -> None:
        encoder = self.model.clip.vision_model.encoder
        compute = self._running.compute
        trunk = compute.trunk if isinstance(compute, TorchCompute) else None
        run = {id(layer) for layer in trunk.layers} if trunk is not None else set()  # fp32 shares the layers
        for layer in encoder.layers:
            if id(layer) not in run:
                for tensor in [*layer.parameters(), *layer.buffers()]:
                    release_pages(tensor)
        encoder.layers = torch.nn.ModuleList(layer for layer in encoder.layers if id(layer) in run)
        gc.collect()

    # ---- per anchor set ------------------------------------------------------------------------------
    @torch.inference_mode()
    def prepare(self, concepts: Sequence[str]) -> torch.Tensor:
        """Text-conditional embeddings (n, projection_dim), cached per tuple of concepts."""
        key = tuple(concepts)
        with self._prepare_lock:
            if key in self._prepared:
                self._prepared.move_to_end(key)
                return self._prepared[key]
            tokens = self.tokenizer(list(key), padding=True, return_tensors="pt").to(self.device)
            embeddings = self.model.get_conditional_embeddings(
                batch_size=len(key), input_ids=tokens["input_ids"], attention_mask=tokens["attention_mask"]
            )
            self._prepared[key] = embeddings
            while len(self._prepared) > self._prepared_cache_size:
                self._prepared.popitem(last=False)
            return embeddings

    # ---- per image -----------------------------------------------------------------------------------
    @torch.inference_mode()
    def vision_activations(self, pixel_values: torch.Tensor) -> list[torch.Tensor]:
        """Hidden states after each layer in ``extract_layers``; later layers are never run."""
        return self._running.compute.activations(pixel_values)

    @torch.inference_mode()
    def decode(self, activations: list[torch.Tensor], conditional: torch.Tensor) -> torch.Tensor:
        """(n, h, w) fp32 logits from a single image's activations, the decoder batched over concepts."""
        return self._running.compute.decode(activations, conditional).float()

    def logits(self, image_rgb: NDArray[np.uint8], prepared: object) -> NDArray[np.float32]:
        """A frame with the running mode (read once: the whole frame runs in one mode)."""
        with self._frame_lock:
            return self.logits_with(self._running.compute, image_rgb, prepared)

    @torch.inference_mode()
    def logits_with(self, compute: Compute, image_rgb: NDArray[np.uint8], prepared: object) -> NDArray[np.float32]:
        """A frame with the given compute, whatever runs: measurements of the modes use it beside the service."""
        if not isinstance(prepared, torch.Tensor):
            raise TypeError("prepared must come from ClipSegBackend.prepare()")
        pixels = self.preprocess(image_rgb).to(self.device)
        return compute.decode(compute.activations(pixels), prepared).float().cpu().numpy()

    @torch.inference_mode()
    def naive_logits(self, image_rgb: NDArray[np.uint8], concepts: Sequence[str]) -> NDArray[np.float32]:
        """transformers' own forward, the image repeated once per concept: the reference and baseline."""
        if not self.keeps_reference:
            raise RuntimeError("transformers' forward needs the whole model: ClipSegBackend(keep_reference=True)")
        pixels = self.preprocess(image_rgb).to(self.device).repeat(len(concepts), 1, 1, 1)
        tokens = self.tokenizer(list(concepts), padding=True, return_tensors="pt").to(self.device)
        out = self.model(pixel_values=pixels, input_ids=tokens["input_ids"], attention_mask=tokens["attention_mask"])
        logits = out.logits
        if logits.ndim == 2:  # transformers squeezes a batch of one
            logits = logits[None]
        return logits.float().cpu().numpy()
