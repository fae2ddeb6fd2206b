"""Fitting anchor positions and widths to the outcomes the robot met (docs/calibration.md, "The fitter").

Positions: bounded least squares of T = sum_k w_k p_k against the outcome, p in [0, 1], with a ridge toward the
current positions that matters only where an anchor has little weight in the pairs:
    minimise  sum_i (w_i . p - y_i)^2 + sum_k lambda_k (p_k - p0_k)^2,  lambda_k = m0^2 / (mass_k + m0)
(m0 = min_pairs_per_anchor: an anchor without pairs stays put, one with 10 m0 moves within 1 % of its data's
answer). Solved by accelerated projected gradient (FISTA), then exactly on the anchors left strictly inside.

Widths: maximum likelihood of the outcomes under the mixture sum_k w_k N(p_k, sigma_k^2) at the fitted
positions, outcomes at 0 or 1 taken as censored (a velocity score is clipped to [0, 1]), so that the
mixture's quantiles, and U, promise what the outcomes show; one golden-section search per anchor on
log sigma, a few sweeps, then the same shrinkage toward the current width.

scipy is not a dependency: both solvers are small and here.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from gcdtrav.schemas.anchors import Anchor, AnchorSet, anchor_diff
from gcdtrav.schemas.experience import (
    AnchorChange,
    AnchorProposal,
    CalibrationFigures,
    judge_against,
    judge_proposal,
)
from gcdtrav.service.engine.risk import normal_cdf
from gcdtrav.service.experience.calibration import calibration_figures
from gcdtrav.service.experience.pairs import Pairs, concept_key
from numpy.typing import NDArray

MIN_WIDTH, MAX_WIDTH = 0.005, 1.0
CENSORED = 1e-6  # an outcome this close to 0 or 1 is censored there (the score was clipped)
GOLDEN = (math.sqrt(5) - 1) / 2
WIDTH_SWEEPS = 4
GOLDEN_STEPS = 40
MAX_GRADIENT_STEPS = 20_000
PAPER, BEST_IN_HISTORY = "paper's set", "best in history"  # the verdict's baselines besides the current set


@dataclass(frozen=True)
class FitOptions:
    tau: float = 0.3
    held_out_fraction: float = 0.3
    min_pairs_per_anchor: float = 20.0
    fit_widths: bool = True


def ridge_strengths(mass: NDArray[np.float64], min_pairs: float) -> NDArray[np.float64]:
    return np.asarray(min_pairs**2 / (mass + min_pairs) if min_pairs > 0 else np.zeros_like(mass), np.float64)


def bounded_least_squares(
    hessian: NDArray[np.float64], linear: NDArray[np.float64], start: NDArray[np.float64]
) -> NDArray[np.float64]:
    """argmin over [0, 1]^n of 1/2 p'Hp - g'p (H symmetric positive semi-definite)."""
    lipschitz = float(np.linalg.eigvalsh(hessian)[-1]) or 1.0
    p = np.clip(start, 0.0, 1.0)
    momentum, t = p.copy(), 1.0
    for _ in range(MAX_GRADIENT_STEPS):
        step = np.clip(momentum - (hessian @ momentum - linear) / lipschitz, 0.0, 1.0)
        t_next = (1 + math.sqrt(1 + 4 * t * t)) / 2
        momentum = step + (t - 1) / t_next * (step - p)
        if float(np.max(np.abs(step - p))) < 1e-13:
            p = step
            break
        if (step - p) @ (p - momentum) > 0:  # the objective went up: restart the momentum
            momentum, t_next = step.copy(), 1.0
        p, t = step, t_next
    return _polish(hessian, linear, p)


def _polish(hessian: NDArray[np.float64], linear: NDArray[np.float64], p: NDArray[np.float64]) -> NDArray[np.float64]:
    """The exact minimiser with the bound anchors held where the gradient method left them."""
    free = (p > 1e-9) & (p < 1 - 1e-9)
    if not free.any():
        return p
    bound = ~free
    rhs = linear[free] - hessian[np.ix_(free, bound)] @ p[bound]
    try:
        exact = np.linalg.solve(hessian[np.ix_(free, free)], rhs)
    except np.linalg.LinAlgError:
        return p
    if np.all((exact >= 0) & (exact <= 1)):
        p = p.copy()
        p[free] = exact
    return p


def fit_positions(
    weights: NDArray[np.floating], outcomes: NDArray[np.floating], current: NDArray[np.floating], min_pairs: float
) -> NDArray[np.float64]:
    w = np.asarray(weights, np.float64)
    y = np.asarray(outcomes, np.float64)
    p0 = np.asarray(current, np.float64)
    ridge = ridge_strengths(w.sum(axis=0), min_pairs)
    hessian = w.T @ w + np.diag(ridge)
    linear = w.T @ y + ridge * p0
    return bounded_least_squares(hessian, linear, p0)


def _component_likelihoods(y: NDArray[np.float64], position: float, width: float) -> NDArray[np.float64]:
    """Each outcome's likelihood under N(position, width^2): the density inside (0, 1), the tail mass at a
    censored 0 or 1."""
    z = (y - position) / width
    density = np.exp(-0.5 * z * z) / (width * math.sqrt(2 * math.pi))
    low, high = y <= CENSORED, y >= 1 - CENSORED
    out = np.where(low, normal_cdf((0.0 - position) / width), density)
    return np.asarray(np.where(high, 1.0 - normal_cdf((1.0 - position) / width), out), np.float64)


def fit_widths(
    weights: NDArray[np.floating],
    outcomes: NDArray[np.floating],
    positions: NDArray[np.floating],
    current: NDArray[np.floating],
    min_pairs: float,
) -> NDArray[np.float64]:
    """Per-anchor widths maximising the outcomes' (censored) likelihood, shrunk toward ``current``."""
    w = np.asarray(weights, np.float64)
    y = np.asarray(outcomes, np.float64)
    n = w.shape[1]
    widths = np.clip(np.asarray(current, np.float64), MIN_WIDTH, MAX_WIDTH)
    columns = np.stack([_component_likelihoods(y, positions[k], widths[k]) for k in range(n)], axis=1)
    mixture = (w * columns).sum(axis=1)
    for _ in range(WIDTH_SWEEPS):
        for k in range(n):
            if w[:, k].sum() <= 0:
                continue
            rest = mixture - w[:, k] * columns[:, k]

            def loglik(log_width: float, k: int = k, rest: NDArray[np.float64] = rest) -> float:
                column = _component_likelihoods(y, positions[k], math.exp(log_width))
                return float(np.sum(np.log(np.maximum(rest + w[:, k] * column, 1e-300))))

            best = _golden_max(loglik, math.log(MIN_WIDTH), math.log(MAX_WIDTH))
            widths[k] = math.exp(best)
            columns[:, k] = _component_likelihoods(y, positions[k], widths[k])
            mixture = rest + w[:, k] * columns[:, k]
    share = _data_share(w.sum(axis=0), min_pairs)
    return np.asarray(current, np.float64) + share * (widths - np.asarray(current, np.float64))


def _data_share(mass: NDArray[np.float64], min_pairs: float) -> NDArray[np.float64]:
    """How far an estimate moves from the current value to the data's: mass / (mass + lambda)."""
    ridge = ridge_strengths(mass, min_pairs)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(mass + ridge > 0, mass / (mass + ridge), 0.0)


def _golden_max(func: Callable[[float], float], low: float, high: float) -> float:
    a, b = low, high
    c, d = b - GOLDEN * (b - a), a + GOLDEN * (b - a)
    fc, fd = func(c), func(d)
    for _ in range(GOLDEN_STEPS):
        if fc >= fd:
            b, d, fd = d, c, fc
            c = b - GOLDEN * (b - a)
            fc = func(c)
        else:
            a, c, fc = c, d, fd
            d = a + GOLDEN * (b - a)
            fd = func(d)
    return (a + b) / 2


def fitted_set(current: AnchorSet, positions: NDArray[np.float64], widths: NDArray[np.float64]) -> AnchorSet:
    """The current set's concepts at the fitted positions and widths, sorted by position (as a set must be)."""
    rounded = [
        (concept, round(float(p), 4), round(float(s), 4))
        for concept, p, s in zip(current.concepts, positions, widths, strict=True)
    ]
    rounded.sort(key=lambda item: item[1])
    name = current.name if current.name.endswith("-fitted") else f"{current.name}-fitted"
    return AnchorSet(
        name=name[:200],
        default_width=0.0,
        anchors=[Anchor(concept=c, position=p, width=s) for c, p, s in rounded],
    )


def propose(
    pairs: Pairs,
    current: AnchorSet,
    options: FitOptions,
    source: str = "",
    stamp: float = 0.0,
    baselines: Sequence[tuple[str, AnchorSet]] = (),
) -> AnchorProposal:
    """Fit on the earlier pairs, grade current and proposed sets on the later ones and judge the change, also
    against the paper's set and the best of ``baselines`` (``baseline_figures``)."""
    train, held = pairs.time_split(options.held_out_fraction)
    if len(train) == 0:
        raise ValueError("no pairs to fit: drive first (or lower held_out_fraction)")
    w = train.weights_for(current).astype(np.float64)
    y = train.outcomes
    p0, s0 = np.asarray(current.positions, np.float64), np.asarray(current.widths, np.float64)
    positions = fit_positions(w, y, p0, options.min_pairs_per_anchor)
    widths = fit_widths(w, y, positions, s0, options.min_pairs_per_anchor) if options.fit_widths else s0
    proposed = fitted_set(current, positions, widths)
    mass = w.sum(axis=0)
    changes = [
        AnchorChange(
            concept=concept,
            position_before=current.positions[k],
            position_after=proposed.positions[proposed.concepts.index(concept)],
            width_before=current.widths[k],
            width_after=proposed.widths[proposed.concepts.index(concept)],
            pairs=float(mass[k]),
            shrunk=bool(mass[k] < options.min_pairs_per_anchor),
        )
        for k, concept in enumerate(current.concepts)
    ]
    before = calibration_figures(held.weights_for(current), held.outcomes, current, options.tau)
    after = calibration_figures(held.weights_for(proposed), held.outcomes, proposed, options.tau)
    verdict = judge_against(
        judge_proposal(before, after, len(held)), after, baseline_figures(held, current, baselines, options.tau)
    )
    return AnchorProposal(
        stamp=stamp,
        source=source,
        current=current,
        proposed=proposed,
        current_version=current.version,
        proposed_version=proposed.version,
        diff=anchor_diff(current, proposed),
        changes=changes,
        train_pairs=len(train),
        held_out_pairs=len(held),
        before=before,
        after=after,
        verdict=verdict,
        pairs_from=float(pairs.stamps.min()) if len(pairs) else None,
        pairs_until=float(pairs.stamps.max()) if len(pairs) else None,
    )


def baseline_figures(
    held: Pairs, current: AnchorSet, baselines: Sequence[tuple[str, AnchorSet]], tau: float
) -> list[tuple[str, str, CalibrationFigures]]:
    """The figures, on the held-out pairs, of the paper's set and of the history's best set (lowest MAE) among
    ``baselines`` (name "paper's set" or "history", set): only sets of the pairs' concept tuple can be graded
    by them, and the current set is judged already."""
    if len(held) == 0:
        return []
    graded: list[tuple[str, str, CalibrationFigures]] = []
    best: tuple[str, str, CalibrationFigures] | None = None
    seen = {current.version}
    for name, anchors in baselines:
        if anchors.version in seen or concept_key(anchors.concepts) != concept_key(held.concepts):
            continue
        seen.add(anchors.version)
        figures = calibration_figures(held.weights_for(anchors), held.outcomes, anchors, tau)
        if name == PAPER:
            graded.append((PAPER, anchors.version, figures))
        elif figures.mae is not None and (best is None or best[2].mae is None or figures.mae < best[2].mae):
            best = (BEST_IN_HISTORY, anchors.version, figures)
    return graded + ([best] if best is not None else [])
