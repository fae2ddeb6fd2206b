"""A context distribution drawn like the paper's Fig. 2: the mixture density, T ± U, and the anchor weights
with their concepts, axes labelled and a legend. One drawing for `gcdtrav probe --png` and the density panels
of `gcdtrav infer --figure`. Needs matplotlib (imported on use: the client stays light)."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any, BinaryIO

from gcdtrav.schemas.messages import ContextDistribution

LABELLED_WEIGHT = 0.05  # anchors with at least this weight are named above their bar
Colour = str | tuple[float, ...]  # a matplotlib colour: a name or RGB(A)


def pyplot() -> Any:
    """matplotlib.pyplot on the file-only backend; ImportError says what to install."""
    try:
        import matplotlib
    except ImportError:
        raise ImportError("drawing needs matplotlib: pip install matplotlib") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def where(d: ContextDistribution) -> str:
    """Which patch or region of which frame, or which ground-grid cell, a distribution is of, in words."""
    if d.cell is not None:
        return f"cell {d.cell} at {d.cell_xy} m, {d.observations} pixels"
    return f"seq={d.seq} " + (f"patch {d.patch}" if d.patch is not None else f"region {d.region}")


def draw_distribution(
    axis: Any, d: ContextDistribution, title: str, colour: Colour = "tab:blue", accent: Colour = "tab:orange"
) -> None:
    """Draw ``d`` on the matplotlib ``axis``: the density in ``colour`` on the left scale, T and T ± U in
    ``accent``, the anchor weights on a right scale; one legend for both."""
    band = f"T ± U = {d.mean:.2f} ± {d.std:.2f}"
    axis.axvspan(d.mean - d.std, d.mean + d.std, color=accent, alpha=0.15, label=band)
    axis.plot(d.density_x, d.density, color=colour, label="context distribution")
    axis.axvline(d.mean, color=accent, linestyle="--", label="T (mean)")
    if d.alpha is not None and d.quantile is not None:  # the risk measures, from 1.1 writers
        axis.axvline(d.quantile, color="tab:red", linestyle=":", label=f"{d.alpha:g}-quantile = {d.quantile:.2f}")
    if d.alpha is not None and d.cvar is not None:
        axis.axvline(d.cvar, color="tab:red", linestyle="-.", label=f"CVaR {d.alpha:g} = {d.cvar:.2f}")
    weights = axis.twinx()
    positions = [a.position for a in d.anchors]
    weights.bar(positions, d.weights, width=0.012, color="tab:gray", alpha=0.8, label="anchor weights")
    for anchor, weight in zip(d.anchors, d.weights, strict=True):
        if weight >= LABELLED_WEIGHT:
            weights.annotate(anchor.concept, (anchor.position, weight), fontsize=7, rotation=90, va="bottom")
    weights.set_ylabel("anchor weight")
    weights.set_ylim(0, max(1.0, max(d.weights) * 1.3))
    axis.set_xlim(0, 1)
    axis.set_xlabel("traversability (0 = untraversable, 1 = ideal ground)")
    axis.set_ylabel("density")
    axis.set_title(title, fontsize=9)
    handles, labels = axis.get_legend_handles_labels()
    bar_handles, bar_labels = weights.get_legend_handles_labels()
    weights.legend(handles + bar_handles, labels + bar_labels, loc="upper right", fontsize=7)  # above the bars


def save_distribution(d: ContextDistribution, path: Path | BinaryIO) -> None:
    """``d`` alone in a PNG (a file or a binary stream), titled with its source, frame and cell."""
    plt = pyplot()
    figure, axis = plt.subplots(figsize=(6.4, 3.2), dpi=120)
    draw_distribution(axis, d, f"{d.source} {where(d)}")
    figure.tight_layout()
    figure.savefig(path, format="png")
    plt.close(figure)


def distribution_png(d: ContextDistribution) -> bytes:
    """``d`` drawn as by ``save_distribution``, as PNG bytes."""
    stream = io.BytesIO()
    save_distribution(d, stream)
    return stream.getvalue()
