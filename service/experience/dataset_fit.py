"""`gcdtrav eval --fit-anchors`: the experience fitter (fitter.py) on a labelled dataset.

Every sampled pixel of the split (the grid of `gcdtrav eval`) is a pair: its anchor weights (the softmax of the
model's logits there) and the traversability its label maps to. The pairs are ordered by image, the last
``held_out_fraction`` of the images held out (a block, as the robot's later drive would be), the fit made on
the rest, and both sets graded on the held-out pixels. The proposed set is written as YAML that `gcdtrav
anchors set` accepts, beside ``proposal.json`` (the AnchorProposal: diff, figures and verdict); `gcdtrav eval`
prints it as `gcdtrav anchors propose` does (client/commands/experience.py, proposal_lines).
"""

from __future__ import annotations

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
