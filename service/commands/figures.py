"""Pictures of T, U and context distributions for people (`gcdtrav infer`): overlays, the paper's Fig. 2.

The colour maps and the overlay live in gcdtrav.schemas.images, shared with the service's preview and the
torch-free viewer (gcdtrav view).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from gcdtrav.client.commands.density_plot import draw_distribution, pyplot
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.images import colorize_traversability, colorize_uncertainty, overlay
from gcdtrav.service.runtime.queries import distribution_of
from numpy.typing import NDArray

__all__ = ["colorize_traversability", "colorize_uncertainty", "overlay", "save_context_figure"]


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
    """Input, T, U with the probes marked; below, each probe's context distribution (like the paper's Fig. 2),
    drawn as `gcdtrav probe --png` draws it.

    ``weights_at_probes`` is (n, len(probes)); ``probes`` are (x, y) image pixels.
    """
    plt = pyplot()
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
    for k, ax in enumerate(axes[1]):
        if k >= len(probes):
            ax.axis("off")
            continue
        d = distribution_of(np.asarray(weights_at_probes[:, k], np.float32), anchors, title, seq=0, stamp=0.0)
        x, y = probes[k]
        heading = f"({x}, {y}): T={d.mean:.2f}  U={d.std:.2f}  modes={d.modes}"
        draw_distribution(ax, d, heading, colour=colours[k % 10])
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
