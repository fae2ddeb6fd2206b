"""Helpers of the store's tests: pairs and proposals made up for the contract (not fixtures)."""

from __future__ import annotations

import numpy as np
from gcdtrav.schemas.anchors import AnchorSet, anchor_diff
from gcdtrav.schemas.experience import AnchorProposal
from gcdtrav.service.experience.calibration import calibration_figures
from gcdtrav.service.store import PairRecord


def pair(
    concepts: tuple[str, ...], k: int, outcome: float = 0.5, source: str = "cam", version: str = "v1"
) -> PairRecord:
    rng = np.random.default_rng(k)
    weights = rng.random(len(concepts)).astype(np.float32) + np.float32(0.01)
    return PairRecord(concepts, weights / weights.sum(), outcome, 1000.0 + k, k % 2, version, source, "test")


def proposal_of(current: AnchorSet, proposed: AnchorSet) -> AnchorProposal:
    empty = calibration_figures(np.zeros((0, len(current))), np.zeros(0), current, 0.3)
    return AnchorProposal(
        stamp=1.0, source="cam", current=current, proposed=proposed, current_version=current.version,
        proposed_version=proposed.version, diff=anchor_diff(current, proposed), changes=[], train_pairs=0,
        held_out_pairs=0, before=empty, after=empty,
    )  # fmt: skip
