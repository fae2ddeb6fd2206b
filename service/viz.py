"""Pictures of T, U and context distributions for people: overlays, the paper's Fig. 2.

The colour maps live in gcdtrav.schemas.images, shared with the torch-free viewer (gcdtrav view).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.images import colorize_traversability, colorize_uncertainty
from gcdtrav.service.engine import gcd
from numpy.typing import NDArray

__all__ = ["colorize_traversability", "colorize_uncertainty", "overlay", "save_context_figure"]


def overlay(image_rgb: NDArray[np.uint8], colours: NDArray[np.uint8], alpha: float = 0.55) -> NDArray[np.uint8]:
    blended = cv2.addWeighted(image_rgb, 1 - alpha, colours, alpha, 0.0)
    return np.asarray(blended, dtype=np.uint8)


def save_context_figure(
    path: Path,
    image_rgb: NDArray[np.uint8],
    t: NDArray[np.floating],
    u: NDArray[np.floating],
    weights_at_probes: NDArray[np.floating],
    probes: Sequence[tuple[int, int]],
    anchors: AnchorSet,
    title: str = "",
) -> None:
    """Input, T, U with the probes marked; below, each probe's context distribution (like the paper's Fig. 2).

    ``weights_at_probes`` is (n, len(probes)); ``probes`` are (x, y) image pixels.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = [plt.get_cmap("tab10")(i) for i in range(10)]
    columns = max(3, len(probes))
    fig, axes = plt.subplots(2, columns, figsize=(4.2 * columns, 7.5), squeeze=False)
    panels = [
        (image_rgb, "input", None),
        (t, "traversability T", "RdYlGn"),
        (u, "uncertainty U (sigma)", "inferno"),
    ]
    for ax, (data, name, cmap) in zip(axes[0], panels, strict=False):
        shown = ax.imshow(data, cmap=cmap, vmin=0 if cmap else None, vmax=(1 if cmap == "RdYlGn" else None))
        if cmap:
            fig.colorbar(shown, ax=ax, fraction=0.046, pad=0.02)
        for k, (x, y) in enumerate(probes):
            ax.plot(x, y, "o", ms=9, mfc="none", mec=colours[k % 10], mew=2.5)
        ax.set_title(name)
        ax.axis("off")
    for ax in axes[0][3:]:
        ax.axis("off")
    grid = gcd.density_grid()
    positions = np.asarray(anchors.positions)
    widths = np.asarray(anchors.widths)
    for k, ax in enumerate(axes[1]):
        if k >= len(probes):
            ax.axis("off")
            continue
        w = weights_at_probes[:, k]
        density = gcd.mixture_density(w[:, None], positions, widths, grid)[0]
        stats = gcd.mixture_statistics(w[:, None], positions, widths)
        mean, std = float(stats.mean[0]), float(stats.std[0])
        ax.bar(positions, w, width=0.012, color="0.35", label="anchor weights")
        ax2 = ax.twinx()
        ax2.plot(grid, density, color=colours[k % 10], lw=2, label="mixture density")
        ax2.set_yticks([])
        ax.axvline(mean, color="k", ls="--", lw=1)
        ax.axvspan(max(mean - std, 0), min(mean + std, 1), color=colours[k % 10], alpha=0.12)
        x, y = probes[k]
        ax.set_title(f"({x}, {y}): T={mean:.2f}  U={std:.2f}  modes={int(stats.modes[0])}")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
        ax.set_xlabel("traversability")
        ax.set_ylabel("weight")
        top = int(np.argmax(w))
        ax.annotate(
            anchors.concepts[top],
            (positions[top], w[top]),
            textcoords="offset points",
            xytext=(0, 4),
            ha="center",
            fontsize=8,
        )
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
