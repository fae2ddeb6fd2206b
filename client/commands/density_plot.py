"""A context distribution drawn like the paper's Fig. 2: the mixture density, T ± U, and the anchor weights
with their concepts, axes labelled and a legend. One drawing for `gcdtrav probe --png` and the density panels
of `gcdtrav infer --figure`, and one text (``describe``) for `gcdtrav probe` and `gcdtrav infer --probe`. Needs
matplotlib to draw (imported on use: the client stays light)."""

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
    frame = f"seq={d.seq} " if d.seq is not None else ""
    if d.patch is not None:
        return f"{frame}patch (row i={d.patch[0]}, column j={d.patch[1]})"
    return f"{frame}region {d.region} (i0, j0, i1, j1: rows and columns, end exclusive)"


def describe(d: ContextDistribution, pixel: tuple[float, float] | None = None) -> str:
    """A distribution as text: T, U, shape, and a bar per anchor weight; ``pixel``: the (x, y) asked for."""
    asked = f"pixel (x={pixel[0]:g}, y={pixel[1]:g}) in " if pixel is not None else ""
    lines = [
        f"{d.source} {asked}{where(d)} anchors={d.anchor_set_version}",
        f"T (mean) = {d.mean:.3f}   U (std) = {d.std:.3f}   modes = {d.modes}   entropy = {d.entropy:.2f} nats",
        f"skewness = {d.skewness:.2f}   excess kurtosis = {d.excess_kurtosis:.2f}",
    ]
    if d.cvar is not None and d.quantile is not None and d.p_below is not None:
        lines.append(
            f"CVaR(alpha={d.alpha:g}) = {d.cvar:.3f}   quantile(alpha) = {d.quantile:.3f}   "
            f"P(T < {d.tau:g}) = {d.p_below:.3f}" + (f"   match = {d.match:.2f}" if d.match is not None else "")
        )
    for anchor, weight in zip(d.anchors, d.weights, strict=True):
        lines.append(f"  {anchor.concept:>14} @ {anchor.position:4.2f}  {weight:6.3f} {'#' * round(weight * 40)}")
    return "\n".join(lines)


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
