"""The paper's evaluation figures: per-class T and U boxplots (Fig. 3), error by method as boxplots and
a swarm coloured by error and sized by uncertainty (Fig. 4), and sparsification curves."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from gcdtrav.schemas.config import Method
from gcdtrav.service.eval import metrics
from numpy.typing import NDArray

SWARM_POINTS = 1500  # per method: enough to see the shape, few enough to draw


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def class_boxplots(data: dict[str, NDArray[Any]], names: dict[int, str], method: Method, path: Path) -> None:
    plt = _pyplot()
    classes = sorted(
        set(int(c) for c in np.unique(data["class"])), key=lambda c: float(data["gt"][data["class"] == c][0])
    )
    labels = [f"{names.get(c, c)}\n(gt {float(data['gt'][data['class'] == c][0]):.2f})" for c in classes]
    fig, axes = plt.subplots(2, 1, figsize=(max(6, 0.9 * len(classes) + 2), 7), sharex=True)
    for ax, key, title in ((axes[0], "T", "traversability T"), (axes[1], "U", "uncertainty U")):
        values = [data[f"{key}_{method.value}"][data["class"] == c] for c in classes]
        ax.boxplot(values, showfliers=False)
        ax.set_ylabel(title)
        ax.grid(axis="y", alpha=0.3)
    axes[0].set_ylim(0, 1)
    axes[1].set_xticks(range(1, len(classes) + 1), labels, rotation=45, ha="right", fontsize=8)
    fig.suptitle(f"T and U per ground-truth class ({method.value})")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def error_by_method(data: dict[str, NDArray[Any]], methods: Sequence[Method], path: Path) -> None:
    plt = _pyplot()
    rng = np.random.default_rng(0)
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(2.6 * len(methods) + 3, 8))
    errors = [np.abs(data[f"T_{m.value}"] - data["gt"]) for m in methods]
    for k, method in enumerate(methods):
        t, u, err = data[f"T_{method.value}"], data[f"U_{method.value}"], errors[k]
        pick = rng.choice(len(t), size=min(SWARM_POINTS, len(t)), replace=False)
        # Horizontal offset grows with the error: low-error points sit to the left of their cluster.
        x = k + 0.7 * (err[pick] / max(float(err.max()), 1e-9)) - 0.35 + rng.uniform(-0.03, 0.03, len(pick))
        size = 4 + 60 * u[pick] / max(float(u.max()), 1e-9)
        shown = top.scatter(x, t[pick], c=err[pick], s=size, cmap="viridis_r", vmin=0, vmax=1, alpha=0.6, linewidths=0)
    fig.colorbar(shown, ax=top, label="|T - ground truth|")
    top.set_xticks(range(len(methods)), [m.value for m in methods])
    top.set_ylabel("predicted T")
    top.set_ylim(0, 1)
    top.set_title("predictions: left = low error, colour = error, size = uncertainty")
    bottom.boxplot(errors, showfliers=False)
    bottom.set_xticks(range(1, len(methods) + 1), [m.value for m in methods])
    bottom.set_ylabel("|T - ground truth|")
    bottom.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def sparsification(data: dict[str, NDArray[Any]], methods: Sequence[Method], path: Path) -> None:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for method in methods:
        error = data[f"T_{method.value}"] - data["gt"]
        fractions, curve = metrics.sparsification_curve(error, data[f"U_{method.value}"])
        _, oracle = metrics.sparsification_curve(error, np.abs(error))
        line = ax.plot(fractions, curve, label=f"{method.value} (by U)")[0]
        ax.plot(fractions, oracle, ls="--", color=line.get_color(), alpha=0.6, label=f"{method.value} oracle")
    ax.set_xlabel("fraction of pixels removed (most uncertain first)")
    ax.set_ylabel("MAE of the remaining pixels")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_figures(data: dict[str, NDArray[Any]], names: dict[int, str], methods: Sequence[Method], out: Path) -> None:
    for method in methods:
        class_boxplots(data, names, method, out / f"fig_class_boxplots_{method.value}.png")
    error_by_method(data, methods, out / "fig_error_by_method.png")
    sparsification(data, methods, out / "fig_sparsification.png")
