"""One drawing of a context distribution, legend and axes labelled, for `gcdtrav probe --png` and the
density panels of `gcdtrav infer --figure`."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from gcdtrav.client.commands import density_plot
from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.service.commands import figures as viz
from gcdtrav.service.runtime.queries import distribution_of

PAPER = default_anchor_set()
LEGEND = ["context distribution", "T (mean)", "anchor weights"]


def weights(top: int) -> np.ndarray:
    w = np.full(len(PAPER), 0.02, np.float32)
    w[top] = 1.0
    return w / w.sum()


def test_the_drawing_has_a_legend_and_labelled_axes() -> None:
    plt = density_plot.pyplot()
    figure, axis = plt.subplots()
    density_plot.draw_distribution(axis, distribution_of(weights(3), PAPER, "cam", 7, 0.0, patch=(1, 2)), "t")
    weights_axis = figure.axes[1]
    texts = [text.get_text() for text in weights_axis.get_legend().get_texts()]
    assert all(any(text.startswith(label) for text in texts) for label in LEGEND) and texts[0].startswith("T ± U")
    assert axis.get_xlabel().startswith("traversability") and axis.get_ylabel() == "density"
    assert weights_axis.get_ylabel() == "anchor weight"
    plt.close(figure)


def test_infer_figure_draws_each_probe_with_the_probe_drawing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    drawn: list[str] = []

    def spy(axis, d, title, **kwargs):  # type: ignore[no-untyped-def]
        drawn.append(title)
        density_plot.draw_distribution(axis, d, title, **kwargs)

    monkeypatch.setattr(viz, "draw_distribution", spy)
    image = np.zeros((20, 30, 3), np.uint8)
    t = np.full((20, 30), 0.5, np.float32)
    probes = [(1, 2), (29, 19)]
    stacked = np.stack([weights(0), weights(12)], axis=1)
    viz.save_context_figure(tmp_path / "figure.png", image, t, t / 4, stacked, probes, PAPER, title="scene")
    assert (tmp_path / "figure.png").stat().st_size > 0
    assert [title.split(":")[0] for title in drawn] == ["(1, 2)", "(29, 19)"]
