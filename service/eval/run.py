"""`gcdtrav eval`: T and U against label-derived ground truth, for the GCD and the paper's baselines.

Per image: one backend forward, then every method on the same logits at the sampled pixels (a fixed grid,
every ``grid`` pixels), so a whole split fits in memory. Per-image results are cached: an interrupted run
resumes where it stopped.
"""

from __future__ import annotations

import csv
import hashlib
import json
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.config import EngineSettings, Method
from gcdtrav.schemas.images import ImageDecodeError, decode_image
from gcdtrav.service.backends.base import SegmentationBackend
from gcdtrav.service.engine.maps import compute_maps
from gcdtrav.service.eval import metrics
from gcdtrav.service.eval.datasets import Dataset, DatasetError, Sample
from gcdtrav.service.eval.mapping import ground_truth
from numpy.typing import NDArray


@dataclass(frozen=True)
class EvalOptions:
    out_dir: Path
    methods: Sequence[Method] = (Method.GCD, Method.ARGMAX, Method.GAUSSIAN)
    grid: int = 8
    limit: int | None = None
    temperature: float = 1.0
    figures: bool = True


def grid_points(height: int, width: int, step: int) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Pixel rows and columns of the sampling grid (cell centres), flattened."""
    ys, xs = np.meshgrid(np.arange(step // 2, height, step), np.arange(step // 2, width, step), indexing="ij")
    return ys.ravel(), xs.ravel()


def evaluate_image(
    backend: SegmentationBackend,
    prepared: object,
    anchors: AnchorSet,
    sample: Sample,
    options: EvalOptions,
    table: NDArray[np.float32],
) -> dict[str, NDArray[Any]]:
    image = decode_image(sample.image_path.read_bytes())
    ids = sample.read_labels()
    if ids.shape != image.shape[:2]:
        raise DatasetError(f"{sample.name}: label size {ids.shape[::-1]} != image size {image.shape[1::-1]}")
    ys, xs = grid_points(ids.shape[0], ids.shape[1], options.grid)
    truth = ground_truth(ids[ys, xs], table)
    keep = ~np.isnan(truth)
    ys, xs = ys[keep], xs[keep]
    logits = backend.logits(image, prepared)
    h, w = logits.shape[1:]
    rows = np.minimum(ys * h // ids.shape[0], h - 1)
    cols = np.minimum(xs * w // ids.shape[1], w - 1)
    sampled = logits[:, rows, cols]  # every method is per patch, so sampling first changes nothing
    result: dict[str, NDArray[Any]] = {"gt": truth[keep], "class": ids[ys, xs]}
    for method in options.methods:
        maps = compute_maps(sampled, anchors, EngineSettings(method=method, temperature=options.temperature))
        result[f"T_{method.value}"] = maps.traversability
        result[f"U_{method.value}"] = maps.uncertainty
    return result


def cache_dir(options: EvalOptions, model_id: str, anchors: AnchorSet, dataset: Dataset) -> Path:
    """Results depend on these; a change of any of them starts a fresh cache."""
    key = json.dumps(
        [
            model_id,
            anchors.version,
            options.grid,
            options.temperature,
            sorted(m.value for m in options.methods),
            dataset.kind,
        ]
    )
    return options.out_dir / "cache" / hashlib.sha256(key.encode()).hexdigest()[:16]


def collect(
    backend: SegmentationBackend,
    anchors: AnchorSet,
    dataset: Dataset,
    table: NDArray[np.float32],
    options: EvalOptions,
) -> tuple[dict[str, NDArray[Any]], list[str]]:
    from tqdm import tqdm

    cache = cache_dir(options, backend.model_id, anchors, dataset)
    prepared = backend.prepare(anchors.concepts)
    parts: list[dict[str, NDArray[Any]]] = []
    failures: list[str] = []
    samples = dataset.samples[: options.limit] if options.limit else dataset.samples
    for sample in tqdm(samples, desc="eval", unit="img", file=sys.stderr):
        cached = cache / f"{sample.name}.npz"
        if cached.is_file():
            with np.load(cached) as data:
                parts.append({k: data[k] for k in data.files})
            continue
        try:
            result = evaluate_image(backend, prepared, anchors, sample, options, table)
        except (ImageDecodeError, DatasetError, OSError) as err:
            failures.append(f"{sample.image_path}: {err}")
            continue
        cached.parent.mkdir(parents=True, exist_ok=True)
        temporary = cached.with_name(cached.name + ".tmp.npz")
        np.savez(temporary, **result)  # type: ignore[arg-type]
        temporary.replace(cached)  # a run killed mid-write leaves no half file to resume from
        parts.append(result)
    if not parts:
        raise DatasetError("no image could be evaluated" + (": " + "; ".join(failures[:3]) if failures else ""))
    merged = {key: np.concatenate([part[key] for part in parts]) for key in parts[0]}
    return merged, failures


def compute_metrics(
    data: dict[str, NDArray[Any]], class_names: dict[int, str], methods: Sequence[Method]
) -> dict[str, Any]:
    report: dict[str, Any] = {"overall": {}, "per_class": {}}
    classes = sorted(set(int(c) for c in np.unique(data["class"])))
    for method in methods:
        t, u = data[f"T_{method.value}"], data[f"U_{method.value}"]
        error = t - data["gt"]
        report["overall"][method.value] = metrics.summary(error, u)
        per_class = {}
        for index in classes:
            mask = data["class"] == index
            per_class[class_names.get(index, str(index))] = {
                "pixels": int(mask.sum()),
                "ground_truth": float(data["gt"][mask][0]),
                "mae": metrics.mae(error[mask]),
                "rmse": metrics.rmse(error[mask]),
                "T_median": float(np.median(t[mask])),
                "U_median": float(np.median(u[mask])),
            }
        report["per_class"][method.value] = per_class
    return report


def write_tables(report: dict[str, Any], out: Path) -> str:
    (out / "metrics.json").write_text(json.dumps(report, indent=2) + "\n", "utf-8")
    with (out / "per_class.csv").open("w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(["method", "class", "pixels", "ground_truth", "mae", "rmse", "T_median", "U_median"])
        for method, classes in report["per_class"].items():
            for name, row in classes.items():
                writer.writerow(
                    [
                        method,
                        name,
                        row["pixels"],
                        row["ground_truth"],
                        f"{row['mae']:.5f}",
                        f"{row['rmse']:.5f}",
                        f"{row['T_median']:.5f}",
                        f"{row['U_median']:.5f}",
                    ]
                )
    auroc_key = f"auroc_u_error_gt_{metrics.ERROR_THRESHOLD}"
    lines = [
        f"| method | pixels | MAE | RMSE | Spearman(U, abs err) | AUROC U for abs err > {metrics.ERROR_THRESHOLD} "
        "| AUSE | AUSE (relative) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for method, row in report["overall"].items():
        lines.append(
            f"| {method} | {int(row['pixels'])} | {row['mae']:.4f} | {row['rmse']:.4f} | "
            f"{row['spearman_u_abs_error']:.3f} | {row[auroc_key]:.3f} | {row['ause']:.4f} | "
            f"{row['ause_relative']:.3f} |"
        )
    table = "\n".join(lines)
    (out / "summary.md").write_text(
        "# Evaluation summary\n\n" + table + "\n\nPer class: per_class.csv; all numbers: metrics.json.\n", "utf-8"
    )
    return table


def run_eval(
    backend: SegmentationBackend,
    anchors: AnchorSet,
    dataset: Dataset,
    table: NDArray[np.float32],
    options: EvalOptions,
) -> dict[str, Any]:
    options.out_dir.mkdir(parents=True, exist_ok=True)
    data, failures = collect(backend, anchors, dataset, table, options)
    report = compute_metrics(data, dataset.class_names, options.methods)
    report["failures"] = failures
    report["images"] = len(dataset.samples[: options.limit] if options.limit else dataset.samples) - len(failures)
    report["settings"] = {
        "dataset": dataset.kind,
        "model": backend.model_id,
        "anchor_set_version": anchors.version,
        "grid": options.grid,
        "temperature": options.temperature,
    }
    report["summary_table"] = write_tables(report, options.out_dir)
    if options.figures:
        from gcdtrav.service.eval.figures import write_figures

        write_figures(data, dataset.class_names, options.methods, options.out_dir)
    return report
