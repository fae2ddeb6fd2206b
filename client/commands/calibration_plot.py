"""The reliability diagram of a calibration report (docs/calibration.md), for `gcdtrav calibration --png`:
predicted P(T < tau) against how often the outcome fell below tau, per bin, with the pairs per bin and the
figures in the title. Needs matplotlib, imported on use (the client's base install has none)."""

from __future__ import annotations

from pathlib import Path

from gcdtrav.client.commands.density_plot import pyplot
from gcdtrav.schemas.experience import CalibrationFigures


def _text(value: float | None, digits: int = 3) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def reliability_diagram(figures: CalibrationFigures, path: Path, title: str = "") -> None:
    plt = pyplot()
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(5.5, 6.2), sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    filled = [b for b in figures.reliability if b.count and b.predicted is not None and b.observed is not None]
    top.plot([0, 1], [0, 1], ls="--", color="tab:gray", label="perfectly calibrated")
    top.plot(
        [b.predicted for b in filled], [b.observed for b in filled], "o-", color="tab:blue", label="outcomes per bin"
    )
    top.set_ylabel(f"share of outcomes below tau = {figures.tau:g}")
    top.set_xlim(0, 1)
    top.set_ylim(0, 1)
    top.grid(alpha=0.3)
    top.legend(loc="upper left", fontsize=8)
    coverage = ", ".join(f"q{alpha}: {_text(value, 2)}" for alpha, value in figures.coverage.items())
    top.set_title(
        (title + "\n" if title else "")
        + f"{figures.pairs} pairs, MAE {_text(figures.mae)}, bias {_text(figures.bias)}, ECE {_text(figures.ece)}\n"
        + f"coverage {coverage}",
        fontsize=8,
    )
    bottom.bar(
        [(b.low + b.high) / 2 for b in figures.reliability],
        [b.count for b in figures.reliability],
        width=0.9 / max(len(figures.reliability), 1),
        color="tab:gray",
    )
    bottom.set_ylabel("pairs")
    bottom.set_xlabel(f"predicted P(T < {figures.tau:g})")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
