"""Pairs of a prediction and an outcome: the weights a cell's mixture had (by concept) before the robot drove
there, and how the drive went. One ``Pairs`` holds one concept tuple's pairs; another tuple is another
softmax, never mixed in."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.service.store.records import concept_key
from numpy.typing import NDArray


@dataclass(frozen=True)
class Pairs:
    concepts: tuple[str, ...]  # the weight columns' order (concept_key order in the store)
    weights: NDArray[np.float32]  # (m, n)
    outcomes: NDArray[np.float64]  # (m,) in [0, 1]
    stamps: NDArray[np.float64]  # (m,) the outcome's stamp
    kinds: NDArray[np.uint8]  # (m,) index into OUTCOME_KINDS
    versions: tuple[str, ...]  # (m,) the anchor-set version whose fusion made the prediction
    # (m,) when each reached the store, on the service's clock (one for the fleet; 0: before store schema 4);
    # None: the stamps are on one clock (a dataset)
    arrivals: NDArray[np.float64] | None = None

    def __len__(self) -> int:
        return len(self.outcomes)

    @classmethod
    def empty(cls, concepts: Sequence[str]) -> Pairs:
        return cls(
            tuple(concepts),
            np.zeros((0, len(concepts)), np.float32),
            np.zeros(0),
            np.zeros(0),
            np.zeros(0, np.uint8),
            (),
        )

    def weights_for(self, anchors: AnchorSet) -> NDArray[np.float32]:
        """The weights with columns in ``anchors``' concept order; ValueError for another concept tuple."""
        if concept_key(anchors.concepts) != concept_key(self.concepts):
            raise ValueError(
                f"pairs of concepts {list(self.concepts)} cannot grade an anchor set of {anchors.concepts}"
            )
        column = {concept: k for k, concept in enumerate(self.concepts)}
        return self.weights[:, [column[c] for c in anchors.concepts]]

    def select(self, mask: NDArray[np.bool_] | NDArray[np.intp]) -> Pairs:
        chosen = np.arange(len(self))[mask]
        return Pairs(
            self.concepts,
            self.weights[chosen],
            self.outcomes[chosen],
            self.stamps[chosen],
            self.kinds[chosen],
            tuple(self.versions[i] for i in chosen),
            None if self.arrivals is None else self.arrivals[chosen],
        )

    def time_split(self, held_out_fraction: float) -> tuple[Pairs, Pairs]:
        """(train, held out): the held-out pairs are the latest ``held_out_fraction`` by arrival at the store, a
        block in time, so neighbouring cells of one drive never sit on both sides. Not by the outcomes' stamps:
        each robot stamps by its own clock (an hour ahead, or a bag's sim time), and one robot whose clock runs
        ahead would be most of the held-out pairs that judge a proposal. Pairs of equal arrival (stored before
        schema 4: 0) keep their order, the store's append order."""
        order = np.argsort(self.stamps if self.arrivals is None else self.arrivals, kind="stable")
        held = round(len(self) * held_out_fraction)
        cut = len(self) - held
        return self.select(order[:cut]), self.select(order[cut:])
