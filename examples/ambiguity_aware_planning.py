"""Ambiguity-aware planning: the mean crosses a puddle the CVaR goes round.

    python examples/ambiguity_aware_planning.py [--alpha 0.1] [--tau 0.1] [--weight 10] [--out FIGURE.png]

A ground grid of fused anchor weights (the paper's 13 anchors) built by hand: firm ground (dirt, soil,
cobblestone), a puddle band across the straight route whose cells are split between water (0.02) and
dirt or grass (0.7, 0.5), and rough but unambiguous ground (sand, moss, gravel) at the puddle's north end.
The puddle's mean T is middling, as high as the rough ground's, so a planner on the mean crosses it; its
CVaR is water's, so a planner on the CVaR goes round through the rough ground. Both plans are printed with
the worst cell they cross by each measure, and drawn over the T and CVaR grids into ./ambiguity-aware-planning.png
or --out (docs/ambiguity-aware-planning.png is the one the README shows).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from gcdtrav.client.planning import PlanResult, plan
from gcdtrav.schemas.anchors import AnchorSet, default_anchor_set
from gcdtrav.service.engine import gcd, risk
from numpy.typing import NDArray

ROWS, COLUMNS, RESOLUTION = 80, 120, 0.1  # cells (row = y, column = x), metres per cell
START, GOAL = (36, 4), (36, 115)
NAMES = {"mean": "mean T", "cvar": "CVaR"}
FIGURE = Path("ambiguity-aware-planning.png")  # in the working directory, never into the checkout's docs/
# Each region's anchor weights (by concept); a cell mixes regions by how far inside it lies, plus noise.
FIRM = {"dirt": 0.6, "soil": 0.3, "cobblestone": 0.1}
PUDDLE = {"water": 0.3, "dirt": 0.45, "grass": 0.25}
ROUGH = {"sand": 0.5, "moss": 0.3, "gravel": 0.2}


def region_weights(anchors: AnchorSet, mix: dict[str, float]) -> NDArray[np.float64]:
    weights = np.zeros(len(anchors))
    for concept, weight in mix.items():
        weights[anchors.concepts.index(concept)] = weight
    return weights


def memberships() -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """How much each cell belongs to the puddle and to the rough ground, with soft, wavy edges."""
    i, j = np.indices((ROWS, COLUMNS), dtype=np.float64)
    wavy_edge = 3.0 * np.sin(i / 6.0) + 2.0 * np.sin(i / 2.5 + 1.0)
    across_puddle = np.abs(j - 60.0 - wavy_edge) - 13.0  # < 0 inside the band, in cells
    puddle = np.clip(0.5 - across_puddle / 3.0, 0.0, 1.0) * np.clip((52.0 - i) / 3.0, 0.0, 1.0)
    rough = np.clip((i - 50.0) / 3.0, 0.0, 1.0) * np.clip(0.5 - (np.abs(j - 60.0) - 24.0) / 3.0, 0.0, 1.0)
    return puddle, rough


def fused_weights(anchors: AnchorSet, rng: np.random.Generator) -> NDArray[np.float32]:
    """(13, ROWS, COLUMNS) anchor weights per cell, as a grid's fusion would hold them."""
    puddle, rough = memberships()
    firm = np.clip(1.0 - puddle - rough, 0.0, 1.0)
    weights = sum(
        region_weights(anchors, mix)[:, None, None] * share[None]
        for mix, share in ((FIRM, firm), (PUDDLE, puddle), (ROUGH, rough))
    )
    noisy = np.asarray(weights) * rng.gamma(20.0, 1.0 / 20.0, size=(len(anchors), ROWS, COLUMNS))
    return (noisy / noisy.sum(axis=0)).astype(np.float32)


def metres(cell: tuple[int, int]) -> str:
    return f"({(cell[1] + 0.5) * RESOLUTION:4.1f}, {(cell[0] + 0.5) * RESOLUTION:4.1f}) m"


def report(name: str, result: PlanResult, tau: float) -> str:
    worst = result.worst
    return (
        f"{name:5s} {result.length_m:5.1f} m  cost {result.cost:7.1f}  "
        f"worst T {worst['traversability'].value:.2f} at {metres(worst['traversability'].cell)}, "
        f"CVaR {worst['cvar'].value:.2f} at {metres(worst['cvar'].cell)}, "
        f"P(T < {tau:g}) {worst['p_below'].value:.2f} at {metres(worst['p_below'].cell)}"
    )


def draw(layers: dict[str, NDArray[np.float32]], plans: dict[str, PlanResult], alpha: float, out: Path) -> None:
    extent = (0.0, COLUMNS * RESOLUTION, 0.0, ROWS * RESOLUTION)
    figure, axes = plt.subplots(1, 2, figsize=(13, 4.6), constrained_layout=True)
    panels = (("traversability", "mean traversability T", "T"), ("cvar", f"CVaR of T at alpha = {alpha:g}", "CVaR"))
    styles = {"mean": dict(color="black", linestyle="--"), "cvar": dict(color="royalblue", linestyle="-")}
    for axis, (layer, title, unit) in zip(axes, panels, strict=True):
        image = axis.imshow(layers[layer], origin="lower", extent=extent, cmap="RdYlGn", vmin=0.0, vmax=1.0)
        figure.colorbar(image, ax=axis, shrink=0.85, label=unit)
        for name, result in plans.items():
            cells = np.asarray(result.cells, dtype=np.float64)
            x, y = (cells[:, 1] + 0.5) * RESOLUTION, (cells[:, 0] + 0.5) * RESOLUTION
            label = f"plan on the {NAMES[name]} ({result.length_m:.1f} m)"
            axis.plot(x, y, linewidth=2.2, label=label, **styles[name])
        for cell, marker, label in ((START, "o", "start"), (GOAL, "*", "goal")):
            axis.plot((cell[1] + 0.5) * RESOLUTION, (cell[0] + 0.5) * RESOLUTION, marker, color="white",
                      markeredgecolor="black", markersize=11, label=label)  # fmt: skip
        axis.set(title=title, xlabel="x [m]", ylabel="y [m]")
    axes[0].legend(loc="lower left", fontsize=8, framealpha=0.9)
    figure.suptitle(
        "A puddle (30 % water, the rest dirt or grass): its mean is the rough ground's, its CVaR is water's"
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out, dpi=110)
    plt.close(figure)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--alpha", type=float, default=0.1, help="CVaR's tail probability")
    parser.add_argument("--tau", type=float, default=0.1, help="threshold of P(T < tau)")
    parser.add_argument("--weight", type=float, default=10.0, help="cost weight of the risk")
    parser.add_argument("--out", type=Path, default=FIGURE, help=f"where to write the figure [./{FIGURE}]")
    args = parser.parse_args()
    anchors = default_anchor_set()
    weights = fused_weights(anchors, np.random.default_rng(25))
    mean, _ = gcd.mixture_mean_std(weights, anchors.positions, anchors.widths)
    measures = risk.risk_measures(weights, anchors.positions, anchors.widths, args.alpha, args.tau)
    layers = {"traversability": mean, "cvar": measures.cvar, "p_below": measures.p_below}
    plans = {
        cost: plan(layers, START, GOAL, cost=cost, weight=args.weight, resolution=RESOLUTION)
        for cost in ("mean", "cvar")
    }
    print(
        f"grid {ROWS} x {COLUMNS} cells of {RESOLUTION} m, the paper's {len(anchors)} anchors, weight {args.weight:g}"
    )
    for name, result in plans.items():
        print(report(name, result, args.tau))
    draw(layers, plans, args.alpha, args.out)
    print(f"figure: {args.out}")


if __name__ == "__main__":
    main()
