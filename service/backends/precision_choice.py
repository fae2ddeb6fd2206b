"""``precision: auto``: the fastest mode that passes the parity gate, chosen by measuring them on this machine.

CPU flags do not say which mode is fastest: on an AVX2-only EPYC ONNX Runtime's int8 trunk wins, on an AMX
Xeon torch's bf16 does, and a container's CPU quota changes the picture again. So at start every mode
this machine can run (``machine.available_precisions``, from the table in ``backends/modes.py``) is timed
on a fixed internal input (a synthetic image, the paper's 13 anchors), its T compared with fp32's
(``parity``), and the fastest that passes the gate (p99 |dT| <= 0.02) is used. The figures are logged,
reported in the status reply, and cached in the cache directory under the same kind of key as the ONNX
export (checkpoint, versions, CPU, threads): ONE cache, which ``gcdtrav doctor`` fills and ``infer``,
``eval`` and ``serve`` read, so they all run the mode doctor printed. ``infer`` and ``eval`` measure
before the first image when nothing is cached; ``serve`` starts in fp32 at once and measures in the
background (``measure_then_switch``), unless told to measure before serving.
"""

from __future__ import annotations

import json
import logging
import os
import statistics
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from gcdtrav.schemas.anchors import AnchorSet, default_anchor_set
from gcdtrav.schemas.config import EngineSettings
from gcdtrav.service.backends.timing import interleaved_ms
from gcdtrav.service.engine.maps import compute_maps
from numpy.typing import NDArray

log = logging.getLogger(__name__)

TRAINED_LOGIT_STD = 3.0  # a trained CLIPSeg's logits are a few units and differ across prompts by a few units
PARITY_P99_DT_LIMIT = 0.02
MEASURED_RUNS = 3
PARITY_IMAGES = 2
CHOICE_FORMAT = 2  # bump when what a mode runs changes (2: fused linears chosen by timing)


def synthetic_image(height: int = 480, width: int = 640, seed: int = 0) -> NDArray[np.uint8]:
    """A structured test image (gradients, blocks, noise): the fixed input of measurements and benchmarks."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width]
    image = np.stack([x * 255 // width, y * 255 // height, ((x // 40 + y // 40) % 2) * 200], axis=2)
    return np.clip(image + rng.integers(0, 30, size=image.shape), 0, 255).astype(np.uint8)


def parity(reference: NDArray[np.float32], candidate: NDArray[np.float32], anchors: AnchorSet) -> dict[str, float]:
    """T/U differences of a fast mode against fp32 on the same inputs, at a trained model's logit scale.

    Random weights give logits whose standard deviation is in the hundreds, almost all of it shared by every
    anchor (a per-patch offset the softmax ignores), while the anchors differ by about one unit. Compared
    as they are, the softmax is nearly one-hot and any rounding flips it; rescaled as a whole to a standard
    deviation of 3, the anchors become indistinguishable and no error shows. Neither is a trained model,
    whose logits are a few units and differ across anchors by a few units. So:
      1. the fast mode's error is kept at its relative size: (candidate - reference) * 3 / std(reference),
         which is rescaling the decoder's last (linear) layer so the logits' standard deviation is 3;
      2. it is added to the reference's anchor-dependent part (per-patch mean removed), scaled so that the
         per-patch spread across anchors is 3 (median over patches).
    T and U from both are compared: max and p99 of |dT| and |dU|, and the fraction of patches whose top
    anchor changes.
    """
    error = (candidate - reference) * (TRAINED_LOGIT_STD / float(reference.std()))
    centred = reference - reference.mean(axis=0, keepdims=True)
    trained_like = centred * (TRAINED_LOGIT_STD / float(np.median(centred.std(axis=0))))
    settings = EngineSettings()
    ref = compute_maps(trained_like, anchors, settings)
    cand = compute_maps(trained_like + error, anchors, settings)
    d_t = np.abs(ref.traversability - cand.traversability)
    d_u = np.abs(ref.uncertainty - cand.uncertainty)
    top_changed = np.argmax(ref.weights, axis=0) != np.argmax(cand.weights, axis=0)
    return {
        "max_dT": float(d_t.max()),
        "p99_dT": float(np.percentile(d_t, 99)),
        "max_dU": float(d_u.max()),
        "p99_dU": float(np.percentile(d_u, 99)),
        "top_anchor_changed": float(top_changed.mean()),
        "relative_logit_error": float((candidate - reference).std() / reference.std()),
    }


@dataclass(frozen=True)
class ModeMeasurement:
    mode: str
    ms_per_frame: float | None  # None: the mode could not be built here
    p99_dT: float | None
    error: str = ""

    @property
    def passes(self) -> bool:
        return self.ms_per_frame is not None and self.p99_dT is not None and self.p99_dT <= PARITY_P99_DT_LIMIT


@dataclass(frozen=True)
class PrecisionChoice:
    mode: str
    reason: str
    measurements: list[ModeMeasurement]


class MeasurementCancelled(Exception):
    """The service is shutting down: the measurement stops between modes, and nothing is cached."""


def measure_modes(
    backend: Any, modes: list[str], runs: int = MEASURED_RUNS, cancelled: Callable[[], bool] = lambda: False
) -> list[ModeMeasurement]:
    """Median ms per frame and p99 |dT| against fp32 of each mode, on the backend's loaded weights. Each mode's
    compute is built and run beside the one the backend runs, which keeps serving; one at a time, so at
    most the reference and one candidate are in memory. ``cancelled`` is asked before each mode."""
    anchors = default_anchor_set()
    images = [synthetic_image(seed=seed) for seed in range(PARITY_IMAGES)]
    reference_compute = backend.compute_for("fp32")
    prepared = backend.prepare(anchors.concepts)
    references = [backend.logits_with(reference_compute, image, prepared) for image in images]
    results = []
    for mode in modes:
        if cancelled():
            raise MeasurementCancelled
        try:
            compute = reference_compute if mode == "fp32" else backend.compute_for(mode)
        except Exception as err:  # an export or a runtime that fails here must not stop the service
            log.warning("precision %s is unavailable here: %s", mode, err)
            results.append(ModeMeasurement(mode, None, None, f"{type(err).__name__}: {err}"[:300]))
            continue
        run = partial(backend.logits_with, compute)
        outputs = [run(images[0], prepared)]  # warm-up (first-call allocations), and parity
        times = interleaved_ms({mode: partial(run, images[0], prepared)}, runs, warmup=0)[mode]
        outputs += [run(image, prepared) for image in images[1:]]
        worst = max(parity(r, o, anchors)["p99_dT"] for r, o in zip(references, outputs, strict=True))
        results.append(ModeMeasurement(mode, round(statistics.median(times), 1), round(worst, 5)))
        log.info("precision %-12s %8.1f ms/frame, p99 |dT| %.4f", mode, results[-1].ms_per_frame, worst)
        del compute, run
    return results


def pick(measurements: list[ModeMeasurement]) -> PrecisionChoice:
    """The fastest mode within the parity gate; fp32 (the reference) when nothing else passes."""
    passing = [m for m in measurements if m.passes]
    best = min(passing, key=lambda m: m.ms_per_frame or float("inf"), default=None)
    figures = ", ".join(
        f"{m.mode} {m.ms_per_frame:.0f} ms" + ("" if m.passes else f" (fails parity, p99 |dT| {m.p99_dT:.3f})")
        for m in measurements
        if m.ms_per_frame is not None and m.p99_dT is not None
    )
    if best is None:
        return PrecisionChoice("fp32", f"auto: no mode could be measured ({figures or 'none ran'}); fp32", measurements)
    reason = (
        f"auto: fastest within the parity gate (p99 |dT| {best.p99_dT:.4f} <= {PARITY_P99_DT_LIMIT}) "
        f"on this machine: {figures}"
    )
    return PrecisionChoice(best.mode, reason, measurements)


def choice_key(backend: Any, modes: list[str]) -> dict[str, Any]:
    import torch
    from gcdtrav.service.backends.cpus import cpu_features
    from gcdtrav.service.backends.onnx_runtime import EXPORT_FORMAT, checkpoint_digests

    checkpoint = backend.checkpoint_dir
    files = checkpoint_digests(checkpoint) if checkpoint is not None else {}
    return {
        "format": CHOICE_FORMAT,
        "checkpoint": files or backend.model_id,
        "modes": modes,
        "input_size": backend.preprocess.size,
        "threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "onnx_export": EXPORT_FORMAT,  # a faster export of the same model can change the pick
        "cpu": cpu_features(),
    }


def _cached(path: Path, key: dict[str, Any]) -> PrecisionChoice | None:
    try:
        stored = json.loads(path.read_text("utf-8"))
        if stored["key"] != key:
            return None
        measurements = [ModeMeasurement(**m) for m in stored["measurements"]]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    choice = pick(measurements)
    measured = stored.get("measured", "earlier")
    return PrecisionChoice(choice.mode, f"{choice.reason} (measured {measured}, cached)", measurements)


def _store(path: Path, key: dict[str, Any], measurements: list[ModeMeasurement]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    record = {
        "key": key,
        "measured": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "measurements": [asdict(m) for m in measurements],
    }
    temporary.write_text(json.dumps(record, indent=1), "utf-8")
    os.replace(temporary, path)


def choice_path(backend: Any, key: dict[str, Any]) -> Path:
    from gcdtrav.service.backends.onnx_runtime import key_digest

    return Path(backend.cache_dir) / "precision" / f"{key_digest(key)}.json"


def cached_choice(backend: Any, modes: list[str]) -> PrecisionChoice | None:
    """auto's choice from the measurement cached for this checkpoint and machine; None if there is none."""
    key = choice_key(backend, modes)
    choice = _cached(choice_path(backend, key), key)
    if choice is not None:
        log.info("precision %s: %s", choice.mode, choice.reason)
    return choice


def measure_and_store(
    backend: Any, modes: list[str], runs: int = MEASURED_RUNS, cancelled: Callable[[], bool] = lambda: False
) -> PrecisionChoice:
    """Measure every mode now, cache the figures (the one cache every command reads) and pick."""
    key = choice_key(backend, modes)
    path = choice_path(backend, key)
    log.info("precision auto: timing %s on this machine (once; cached in %s) ...", ", ".join(modes), path.parent)
    measurements = measure_modes(backend, modes, runs, cancelled=cancelled)
    try:
        _store(path, key, measurements)
    except OSError as err:
        log.warning("cannot cache the precision measurements in %s: %s", path, err)
    choice = pick(measurements)
    log.info("precision %s: %s", choice.mode, choice.reason)
    return choice


def measure_then_switch(backend: Any, modes: list[str], cancel: threading.Event | None = None) -> None:
    """Measure the modes while the backend serves in its safe mode, then switch it to auto's choice between
    frames. ``backend.measuring`` is true meanwhile. A failure leaves the safe mode running, with the reason;
    ``cancel`` set (shutdown) stops it before the next mode, caching nothing."""
    backend.measuring = True
    stop = cancel or threading.Event()
    try:
        choice = measure_and_store(backend, modes, cancelled=stop.is_set)
        compute = backend.compute if choice.mode == backend.precision else backend.compute_for(choice.mode)
        backend.switch_to(compute, choice.mode, choice.reason)
        log.info("precision switched to %s", choice.mode)
    except MeasurementCancelled:
        log.info("precision auto: measurement stopped by the shutdown; nothing cached")
    except Exception as err:  # the service keeps serving in the safe mode
        log.exception("precision auto: the measurement failed; staying on %s", backend.precision)
        reason = f"auto: the measurement failed ({err}); {backend.precision}"
        backend.use_compute(backend.compute, backend.precision, reason)
    finally:
        backend.measuring = False
        backend.needs_measurement = False


@dataclass
class BackgroundMeasurement:
    """``measure_then_switch`` in a daemon thread, and how to stop it at shutdown."""

    thread: threading.Thread
    cancel: threading.Event

    def join(self, timeout: float | None = None) -> bool:
        """True once the measurement has ended."""
        self.thread.join(timeout)
        return not self.thread.is_alive()

    def stop(self, timeout: float) -> bool:
        """Cancel (effective before the next mode) and wait; False if it is still inside one (an ONNX export)."""
        self.cancel.set()
        return self.join(timeout)


def measure_in_background(backend: Any) -> BackgroundMeasurement:
    from gcdtrav.service.backends.machine import available_precisions

    backend.measuring = True  # before the thread starts: a status asked right now already says so
    cancel = threading.Event()
    thread = threading.Thread(
        target=measure_then_switch, args=(backend, available_precisions(), cancel), name="precision-auto", daemon=True
    )
    thread.start()
    return BackgroundMeasurement(thread, cancel)
