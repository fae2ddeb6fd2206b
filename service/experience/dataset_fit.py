"""`gcdtrav eval --fit-anchors`: the experience fitter (fitter.py) on a labelled dataset.

Every sampled pixel of the split (the grid of `gcdtrav eval`) is a pair: its anchor weights (the softmax of the
model's logits there) and the traversability its label maps to. The pairs are ordered by image, the last
``held_out_fraction`` of the images held out (a block, as the robot's later drive would be), the fit made on
the rest, and both sets graded on the held-out pixels. The proposed set is written as YAML that `gcdtrav
anchors set` accepts, beside ``proposal.json`` (the AnchorProposal, diff and figures included).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.experience import OUTCOME_KINDS, AnchorProposal
from gcdtrav.schemas.images import ImageDecodeError, decode_image
from gcdtrav.service.backends.base import SegmentationBackend
from gcdtrav.service.engine.gcd import softmax_weights
from gcdtrav.service.eval.datasets import Dataset, DatasetError
from gcdtrav.service.eval.mapping import ground_truth
from gcdtrav.service.eval.run import grid_points
from gcdtrav.service.experience.fitter import FitOptions, propose
from gcdtrav.service.experience.pairs import Pairs
from numpy.typing import NDArray

PROPOSED_FILE = "proposed-anchors.yaml"
PROPOSAL_FILE = "proposal.json"


@dataclass(frozen=True)
class FitRun:
    proposal: AnchorProposal
    proposed_file: Path
    failures: list[str]


def labelled_pairs(
    backend: SegmentationBackend,
    anchors: AnchorSet,
    dataset: Dataset,
    table: NDArray[np.float32],
    grid: int,
    temperature: float,
    limit: int | None,
) -> tuple[Pairs, list[str]]:
    """Weights and label traversability of every sampled pixel; the image's index is the pair's stamp."""
    prepared = backend.prepare(anchors.concepts)
    weights, truth, stamps, failures = [], [], [], []
    for index, sample in enumerate(dataset.samples[:limit] if limit else dataset.samples):
        try:
            image = decode_image(sample.image_path.read_bytes())
            ids = sample.read_labels()
        except (ImageDecodeError, DatasetError, OSError) as err:
            failures.append(f"{sample.image_path}: {err}")
            continue
        ys, xs = grid_points(ids.shape[0], ids.shape[1], grid)
        values = ground_truth(ids[ys, xs], table)
        keep = ~np.isnan(values)
        logits = backend.logits(image, prepared)
        h, w = logits.shape[1:]
        rows = np.minimum(ys[keep] * h // ids.shape[0], h - 1)
        cols = np.minimum(xs[keep] * w // ids.shape[1], w - 1)
        weights.append(softmax_weights(logits[:, rows, cols], temperature).T)
        truth.append(values[keep].astype(np.float64))
        stamps.append(np.full(int(keep.sum()), float(index)))
    if not weights:
        raise DatasetError("no image could be read" + (": " + "; ".join(failures[:3]) if failures else ""))
    count = sum(len(t) for t in truth)
    pairs = Pairs(
        tuple(anchors.concepts),
        np.concatenate(weights).astype(np.float32),
        np.concatenate(truth),
        np.concatenate(stamps),
        np.full(count, OUTCOME_KINDS.index("operator"), np.uint8),  # a person's labels
        (anchors.version,) * count,
    )
    return pairs, failures


def fit_on_dataset(
    backend: SegmentationBackend,
    anchors: AnchorSet,
    dataset: Dataset,
    table: NDArray[np.float32],
    out_dir: Path,
    options: FitOptions,
    grid: int = 8,
    temperature: float = 1.0,
    limit: int | None = None,
) -> FitRun:
    pairs, failures = labelled_pairs(backend, anchors, dataset, table, grid, temperature, limit)
    proposal = propose(pairs, anchors, options, source=f"eval {dataset.kind}")
    out_dir.mkdir(parents=True, exist_ok=True)
    proposed_file = out_dir / PROPOSED_FILE
    proposal.proposed.save(proposed_file)
    (out_dir / PROPOSAL_FILE).write_text(proposal.model_dump_json(indent=2) + "\n", "utf-8")
    return FitRun(proposal, proposed_file, failures)


def summary(run: FitRun) -> str:
    """The diff and the held-out figures before and after, for the terminal."""
    p = run.proposal
    lines = [f"{p.current_version} ({len(p.current)} anchors) -> {p.proposed_version} ({len(p.proposed)} anchors)"]
    lines += p.diff or ["no change"]
    lines += [
        "",
        f"held-out pixels: {p.held_out_pairs} (fitted on {p.train_pairs})",
        "| set | MAE | bias | coverage q0.05 / q0.1 / q0.2 | ECE |",
        "|---|---|---|---|---|",
    ]
    for name, figures in (("current", p.before), ("proposed", p.after)):
        coverage = " / ".join("-" if v is None else f"{v:.3f}" for v in figures.coverage.values())
        mae = "-" if figures.mae is None else f"{figures.mae:.4f}"
        bias = "-" if figures.bias is None else f"{figures.bias:+.4f}"
        ece = "-" if figures.ece is None else f"{figures.ece:.4f}"
        lines.append(f"| {name} | {mae} | {bias} | {coverage} | {ece} |")
    lines += ["", f"proposed set: {run.proposed_file} (gcdtrav anchors set {run.proposed_file} --dry-run)"]
    return "\n".join(lines)


def print_summary(run: FitRun) -> None:
    for failure in run.failures:
        print(f"error: {failure}", file=sys.stderr)
    print(summary(run))
