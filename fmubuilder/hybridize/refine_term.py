"""The fitted term's coefficient refined through the simulation.

The diagnosis fits the term's coefficient by a regression on closed-loop responses linearised
around the plain model (diagnose/trace.py): for a strong effect the loop's response is not linear
in the term, and a small bias of the coefficient grows in the signals that integrate it (an
energy, a temperature). Here the term's scale is fitted on the training data by the simulation
itself, as a nonlinear least-squares problem:

    parameters -> one scale per derivative the term corrects: the exported hybrid FMU's gate
                  (`hybrid.<x>.p_term`) set as a start value: the model simulated is the FMU
                  that would be published, with no second implementation
    residuals  -> (the model's signals seen through the sensor lag - measured) / noise level
    simulation -> DOPRI5 at ACCURATE_RTOL: the coefficient describes the model, not a fixed
                  step's discretisation error
    search     -> Levenberg-Marquardt with finite differences, at most MAX_SIMULATIONS simulations,
                  kept only if it lowers the training objective (the README's "The candidates")
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..data import MeasuredData
from ..progress import progress
from .evaluate import Objective, Runs, Scoring

# Simulations of the training data (each of its runs once) in all: the unrefined term's, then per
# iteration one per scale and one or more trials.
MAX_SIMULATIONS = 10
ACCURATE_RTOL = 1e-7
# Finite-difference step of a scale, relative; later the size of the last step, down to the minimum.
PERTURBATION = 0.1
MIN_PERTURBATION = 1e-3
# Levenberg-Marquardt damping (Marquardt's: relative to the diagonal of J^T J), and its factor.
DAMPING = 1e-3
DAMPING_FACTOR = 10.0
# Converged when a step changes every scale by less than this (relative): the next would change it
# far less (the finite difference then spans the last step, so the steps shrink faster than linearly).
STEP_TOLERANCE = 1e-3

@dataclass
class Refinement:
    """The term's scales after the refinement (all 1 when it was not kept)."""
    gates: list[str]
    scales: list[float]
    objective_before: float     # mean squared residual in noise units, unrefined term
    objective_after: float      # the same with the scales (equal when not kept)
    simulations: int
    kept: bool

    def to_dict(self) -> dict:
        return {"gates": self.gates, "scales": self.scales, "objective_before": _finite(self.objective_before),
                "objective_after": _finite(self.objective_after), "simulations": self.simulations, "kept": self.kept}


def _finite(value: float) -> float | None:
    """A number for the JSON report, which has no infinity (a term that does not simulate)."""
    return value if math.isfinite(value) else None


def refine_scales(hybrid_fmu, gates: list[str], runs: Runs, noise: dict[str, float], output_step: float, *,
                  budget: int = MAX_SIMULATIONS, show: bool = True) -> Refinement:
    """Levenberg-Marquardt on the scales of a hybrid FMU's gates (start 1: the term as exported).
    noise: the noise level of each measured signal (per sample); output_step: the grid on which the
    sensor lag is applied (the scoring's step)."""
    objective = Objective(hybrid_fmu, runs, Scoring.accurate(output_step, ACCURATE_RTOL))
    objective.units = objective.per_signal(lambda data, name: noise_level(noise, name, data))
    start = np.ones(len(gates))
    with progress(budget, "refining the fitted term through the simulation", "simulation", show=show) as bar:
        objective.bar = bar
        residual = _residuals(objective, gates, start)
        if residual is None:       # the term as exported does not simulate: nothing to refine from
            bar.stop("the hybrid does not simulate over the training data")
            return Refinement(gates, start.tolist(), math.inf, math.inf, objective.simulations, False)
        scales, after, ended = levenberg_marquardt(objective, gates, start, residual, budget)
        bar.stop(ended)
    before = _cost(residual)
    kept = after < before
    return Refinement(gates, [float(s) for s in (scales if kept else start)], before, after if kept else before,
                      objective.simulations, kept)


def levenberg_marquardt(objective: Objective, gates: list[str], scales: np.ndarray, residual: np.ndarray,
                        budget: int):
    """(scales, their objective, why it ended before the budget). `objective` is anything with
    `simulations` (spent so far) and `errors({gate: scale})` (residuals, None where a run fails), an
    Objective here, term_forms.TermObjective for the forms of a term."""
    cost = _cost(residual)
    damping, relative_delta = DAMPING, PERTURBATION
    n = scales.size
    while objective.simulations + n + 1 <= budget:
        jacobian = _jacobian(objective, gates, scales, residual, relative_delta)
        if jacobian is None:
            return scales, cost, "a perturbed run failed"
        gradient, curvature = jacobian.T @ residual, jacobian.T @ jacobian
        if not np.any(np.diag(curvature) > 0):
            return scales, cost, "the term does not move the signals"
        accepted = False
        while objective.simulations < budget:
            step = np.linalg.solve(curvature + damping * np.diag(np.diag(curvature)) + 1e-300 * np.eye(n), -gradient)
            trial = _residuals(objective, gates, scales + step)
            if trial is not None and _cost(trial) < cost:
                scales, residual, cost, accepted = scales + step, trial, _cost(trial), True
                damping /= DAMPING_FACTOR
                break
            damping *= DAMPING_FACTOR
        if not accepted:
            return scales, cost, "no lower training error found"
        relative = float(np.max(np.abs(step) / np.maximum(np.abs(scales), 1e-12)))
        if relative < STEP_TOLERANCE:
            return scales, cost, "converged"
        relative_delta = min(PERTURBATION, max(MIN_PERTURBATION, relative))
    return scales, cost, "the budget is spent"


def _jacobian(objective: Objective, gates: list[str], scales: np.ndarray, residual: np.ndarray,
              relative_delta: float):
    """Forward differences, one simulation per scale; None when a perturbed run fails."""
    columns = []
    for k in range(scales.size):
        delta = relative_delta * max(abs(scales[k]), 1e-3)
        perturbed = scales.copy()
        perturbed[k] += delta
        moved = _residuals(objective, gates, perturbed)
        if moved is None:
            return None
        columns.append((moved - residual) / delta)
    return np.column_stack(columns)


def _residuals(objective: Objective, gates: list[str], scales: np.ndarray) -> np.ndarray | None:
    """The residuals in noise units with the gates at `scales`: one simulation of the training data."""
    return objective.errors(dict(zip(gates, map(float, scales))))


def _cost(residual: np.ndarray) -> float:
    return float(residual @ residual) / residual.size


def noise_level(noise: dict[str, float], name: str, data: MeasuredData) -> float:
    """The signal's noise level; a zero or missing one falls back to a tiny share of its range, so
    that a noise-free signal weighs much but finitely."""
    level = noise.get(name, 0.0)
    if level > 0 and math.isfinite(level):
        return float(level)
    return max(1e-9 * float(np.ptp(data.signals[name])), 1e-300)


# -- the term and its gates ---------------------------------------------------------------------

def term_gates(spec) -> list[str]:
    """The gate parameter of each channel of a fitted term's hybrid spec, as the export names them."""
    from ..export.hybrid_description import channel_layouts
    return [layout.p_ann for layout in channel_layouts(spec)]


def scaled_term(fitted: dict, scale: float) -> dict:
    """The diagnosis' fitted term (one channel) with every coefficient times `scale`, its expression
    rewritten."""
    from ..diagnose.runs import AddedTerm
    terms = [{**t, "coefficient": float(t["coefficient"]) * scale} for t in fitted["terms"]]
    text = " + ".join(AddedTerm(0, t["variable"], t["basis"], float(t["center"]), t["coefficient"]).expression()
                      for t in terms).replace("+ -", "- ")
    return {**fitted, "terms": terms, "expression": f"{fitted['channel']} += {text}"}


def coefficients_text(fitted: dict) -> str:
    return ", ".join(f"{float(t['coefficient']):.7g}" for t in fitted["terms"])
