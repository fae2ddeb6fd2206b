"""Monte Carlo check of service/engine/risk.py: quantile, CVaR and P(T < tau) against samples of the mixture.

    python -m benchmarks.risk_mc                              # 20 mixtures, 10^6 samples each
    python -m benchmarks.risk_mc --samples 100000 --mixtures 5 --out /tmp/risk_mc.json

Each mixture has 13 anchors at random positions in [0, 1], about half of them point masses (width 0), the
others Gaussians of width 0.01 to 0.15, with Dirichlet(0.5) weights. For alpha in ALPHAS and tau in TAUS:

- quantile q: the empirical P(T < q) must not exceed alpha, nor P(T <= q) fall short of it, by more than
  the sampling error; also reported: |q - the empirical lower quantile| (0 when q is a point mass);
- CVaR: against the mean of the lowest alpha N samples (the boundary sample weighted by its fraction), with
  the standard error from the mixture's own variance of (q - T)^+ (closed form): a tail of a few samples
  cannot estimate its own spread;
- p_below: against the fraction of samples below tau.

Errors are reported absolute and in standard errors (SE) of the Monte Carlo estimate, less RESOLUTION (the
float32 results' rounding and the solver's tolerance: a tail that is one point mass has an SE of ~0); the
exit code is 1 when any is beyond --max-se.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from gcdtrav.service.engine import risk
from numpy.typing import NDArray

ALPHAS = (0.01, 0.05, 0.1, 0.25, 0.5, 0.9, 1.0)
TAUS = (0.1, 0.3, 0.5, 0.8)
ANCHORS = 13
RESOLUTION = 1e-6


@dataclass
class Agreement:
    """The worst disagreement of one measure over every mixture and parameter."""

    checks: int = 0
    max_abs_error: float = 0.0
    max_error_in_se: float = 0.0
    worst: dict[str, float] = field(default_factory=dict)

    def add(self, error: float, standard_error: float, where: dict[str, float]) -> None:
        self.checks += 1
        beyond = max(error - RESOLUTION, 0.0)
        in_se = beyond / standard_error if standard_error > 0 else (0.0 if beyond == 0 else math.inf)
        self.max_abs_error = max(self.max_abs_error, error)
        if in_se > self.max_error_in_se:
            self.max_error_in_se, self.worst = in_se, where


def random_mixture(rng: np.random.Generator) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    weights = rng.dirichlet(np.full(ANCHORS, 0.5))
    positions = rng.uniform(0.0, 1.0, ANCHORS)
    widths = np.where(rng.random(ANCHORS) < 0.5, 0.0, rng.uniform(0.01, 0.15, ANCHORS))
    return weights, positions, widths


def sample(
    rng: np.random.Generator,
    weights: NDArray[np.float64],
    positions: NDArray[np.float64],
    widths: NDArray[np.float64],
    count: int,
) -> NDArray[np.float64]:
    component = rng.choice(len(weights), size=count, p=weights)
    return np.sort(positions[component] + widths[component] * rng.standard_normal(count))


def shortfall_standard_error(
    weights: NDArray[np.float64],
    positions: NDArray[np.float64],
    widths: NDArray[np.float64],
    q: float,
    alpha: float,
    count: int,
) -> float:
    """The Monte Carlo standard error of q - mean((q - T)^+) / alpha, from the exact variance of (q - T)^+.

    A Gaussian anchor's E[(q - T)^+] = s (z Phi + phi) and E[((q - T)^+)^2] = s^2 ((z^2 + 1) Phi + z phi),
    z = (q - mu) / s; a point mass's are (q - mu)^+ and its square.
    """
    gaussian = widths > 0
    s = np.where(gaussian, widths, 1.0)
    z = (q - positions) / s
    cdf, pdf = risk.normal_cdf(z), np.exp(-0.5 * z * z) / math.sqrt(2 * math.pi)
    gap = np.maximum(q - positions, 0.0)
    first = np.where(gaussian, s * (z * cdf + pdf), gap)
    second = np.where(gaussian, s * s * ((z * z + 1) * cdf + z * pdf), gap * gap)
    variance = max(float(weights @ second) - float(weights @ first) ** 2, 0.0)
    return math.sqrt(variance / count) / alpha


def tail_mean(ordered: NDArray[np.float64], alpha: float) -> float:
    """The mean of the lowest alpha of the (sorted) samples, the boundary sample counted by its fraction."""
    mass = alpha * ordered.size
    whole = math.floor(mass)
    fraction = mass - whole
    boundary = ordered[whole] * fraction if whole < ordered.size else 0.0
    return float((ordered[:whole].sum() + boundary) / mass)


def check_mixture(
    rng: np.random.Generator, count: int, agreements: dict[str, Agreement], index: int, max_quantile_gap: list[float]
) -> None:
    weights, positions, widths = random_mixture(rng)
    ordered = sample(rng, weights, positions, widths, count)
    for alpha in ALPHAS:
        m = risk.risk_measures(weights, positions, widths, alpha, tau=TAUS[0])
        q, c = float(m.quantile), float(m.cvar)
        where = {"mixture": index, "alpha": alpha}
        se = math.sqrt(max(alpha * (1 - alpha), 1.0 / count) / count)
        below, at_most = (
            np.searchsorted(ordered, q - 1e-6, "left") / count,
            np.searchsorted(ordered, q + 1e-6, "right") / count,
        )
        agreements["quantile (error in P)"].add(max(below - alpha, alpha - at_most, 0.0), se, where)
        if alpha < 1:  # at 1, a Gaussian anchor's q is where less than 1e-12 lies above: beyond any sample
            empirical = ordered[max(math.ceil(alpha * count) - 1, 0)]
            max_quantile_gap[0] = max(max_quantile_gap[0], abs(q - empirical))
        se = shortfall_standard_error(weights, positions, widths, q, alpha, count)
        agreements["cvar"].add(abs(c - tail_mean(ordered, alpha)), se, where)
    for tau in TAUS:
        p = float(risk.p_below(weights, positions, widths, tau))
        estimate = np.searchsorted(ordered, tau, "left") / count
        se = math.sqrt(max(p * (1 - p), 1.0 / count) / count)
        agreements["p_below"].add(abs(p - estimate), se, {"mixture": index, "tau": tau})


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--samples", type=int, default=1_000_000)
    parser.add_argument("--mixtures", type=int, default=20)
    parser.add_argument("--seed", type=int, default=20261123)
    parser.add_argument("--max-se", type=float, default=5.0, help="fail beyond this many standard errors")
    parser.add_argument("--out", type=Path, default=None, help="write the results as JSON")
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    agreements = {name: Agreement() for name in ("quantile (error in P)", "cvar", "p_below")}
    max_quantile_gap = [0.0]
    for index in range(args.mixtures):
        check_mixture(rng, args.samples, agreements, index, max_quantile_gap)
    print(f"{args.mixtures} mixtures of {ANCHORS} anchors (about half point masses), {args.samples:,} samples each")
    print("| measure | checks | max abs error | max error / SE | worst at |")
    print("|---|---|---|---|---|")
    for name, a in agreements.items():
        print(f"| {name} | {a.checks} | {a.max_abs_error:.2e} | {a.max_error_in_se:.2f} | {a.worst} |")
    print(
        f"quantile: max |q - empirical lower quantile| = {max_quantile_gap[0]:.2e} for alpha < 1 (checked in P above)"
    )
    if args.out:
        results = {
            "samples": args.samples,
            "mixtures": args.mixtures,
            "seed": args.seed,
            "alphas": ALPHAS,
            "taus": TAUS,
        }
        results |= {name: asdict(a) for name, a in agreements.items()}
        results["max_quantile_gap"] = max_quantile_gap[0]
        args.out.write_text(json.dumps(results, indent=2) + "\n", "utf-8")
    return 0 if all(a.max_error_in_se <= args.max_se for a in agreements.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
