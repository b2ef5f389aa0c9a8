"""Calibration of one FMU parameter: a candidate beside the fitted term and the NeuralFMU, for
models wrong in a number rather than in a missing term (the README's "The candidates").

    screening -> each Real parameter (causality "parameter", variability fixed or tunable, not set
                 by the data's start values) perturbed once by PERTURBATION of its value, over the
                 first SCREEN_SAMPLES samples of the first training run; the change of the signals,
                 regressed on their residual, is its `explained` share (0..1). Parameters whose
                 changes move the signals alike are one candidate, the first of them fitted
    fit       -> the best MAX_CALIBRATED parameters (see RUNNER_UP_SHARE) by Gauss-Newton with step
                 halving on all training runs, at most FIT_SIMULATIONS simulations each (as
                 `evaluate.Objective` counts), within [start / RANGE, start * RANGE]

Every run is scored as the workflow scores candidates (`evaluate`), and the objective is the
workflow's score, so the fit minimises on the training data what the choice compares on the
validation data.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import FmuBuilderError
from .evaluate import Objective, Runs, Scoring

# Relative perturbation of a parameter for its finite-difference sensitivity: of the size of the
# errors sought. A model with events (a driver's relays, a sampled controller) answers a 1 % change
# with shifted event times that hide the parameter's effect (on the VLDM, a 1 % larger mass
# correlates with the speed residual of a 10 % larger one at cos^2 = 0.14, a 10 % one at 0.82).
# The fit shrinks it to its last step, down to MIN_PERTURBATION, as it closes in.
PERTURBATION = 0.1
MIN_PERTURBATION = 0.01
# Samples of the first training run the screening simulates (the diagnosis traces as many).
SCREEN_SAMPLES = 1000
# Parameters fitted after the screening, and simulations (of all training runs) per fit.
MAX_CALIBRATED = 2
FIT_SIMULATIONS = 8
# A screened parameter is fitted when it explains at least MIN_EXPLAINED of the residual and at
# least RUNNER_UP_SHARE of what the leading one explains (a distant runner-up rarely wins).
MIN_EXPLAINED = 0.05
RUNNER_UP_SHARE = 0.5
# Two parameters are equivalent when their sensitivities (the signals' change per unit of each,
# over the screened samples) are parallel within this: 1 - cos^2 of the angle between them. A
# product c * A gives ~1e-12 (the same simulation); the DC drive's R0 and T_ref in
# R0 (1 + alpha (T - T_ref)), alike near T_ref but not as the winding warms, give 7e-3
# over the 6 s of tests/hybridize/test_calibrate.py.
EQUIVALENT_SINE2 = 1e-6
# The fit stays within a factor RANGE of the declared value (same sign).
RANGE = 10.0
# Screened parameters listed in the report.
SCREEN_REPORTED = 5
# The fit stops when a step changes the value by less than this (relative).
STEP_TOLERANCE = 1e-4

@dataclass
class Sensitivity:
    """How far perturbing one parameter goes towards the measured data."""
    name: str
    declared: float
    explained: float          # share of the score the best linear step along this parameter removes
    direction: np.ndarray | None = field(default=None, repr=False)   # the scaled sensitivity
    equivalent: list = field(default_factory=list)   # names of the parameters that act alike, not fitted
    declared_at: int = 0      # position in the model description (the tie-break between twins)

    def acts_like(self, other: "Sensitivity") -> bool:
        """The two change the signals alike: their sensitivities are parallel (EQUIVALENT_SINE2)."""
        if self.direction is None or other.direction is None:
            return False
        a, b = self.direction, other.direction
        cos2 = float(a @ b) ** 2 / (float(a @ a) * float(b @ b))
        return 1.0 - cos2 <= EQUIVALENT_SINE2


@dataclass
class Calibration:
    """One parameter fitted on the training data."""
    name: str
    declared: float
    value: float
    train_score: float        # mean over signals of MSE / MSE plain, on the training samples
    simulations: int

    @property
    def description(self) -> str:
        return f"{self.name} = {self.value:.6g} (declared {self.declared:.6g})"

    def details(self, ranked: list[Sensitivity], fitted_on: str) -> dict:
        """What the report says about this candidate."""
        same = next((s.equivalent for s in ranked if s.name == self.name), [])
        return {"calibrated": {self.name: self.value}, "declared": {self.name: self.declared},
                "equivalent_parameters": list(same), "train_score": self.train_score,
                "simulations": self.simulations, "fitted_on": fitted_on,
                "screening": [{"parameter": s.name, "explained": s.explained} for s in ranked[:SCREEN_REPORTED]]}


def calibratable_parameters(info, fixed_by_data: set[str]) -> list:
    """Real parameters the data leave free, with a non-zero finite start value to perturb from
    (a zero start gives no scale for the perturbation)."""
    chosen = []
    for var in info.parameters:
        if var.causality != "parameter" or var.type != "Real" or var.variability not in ("fixed", "tunable") \
                or var.name in fixed_by_data:
            continue
        try:
            start = float(var.start)
        except (TypeError, ValueError):
            continue
        if start != 0.0 and math.isfinite(start):
            chosen.append(var)
    return chosen


def relative_units(objective: Objective, plain_errors: np.ndarray) -> np.ndarray:
    """Per sample, the unit that makes the squared norm of the errors in it the workflow's score
    (`relative_mse`, the mean over the signals of MSE / MSE plain): sqrt(n_signals * N_s * MSE_plain_s)
    for a signal s of N_s samples over all runs. A signal the plain model matches exactly weighs nothing."""
    names = objective.per_signal(lambda data, name: name)
    mse = {s: float(np.mean(plain_errors[names == s] ** 2)) for s in set(names.tolist())}
    used = max(sum(value > 0 for value in mse.values()), 1)
    return objective.per_signal(lambda data, name: math.sqrt(used * np.count_nonzero(names == name) * mse[name])
                                if mse[name] > 0 else math.inf)


def screen_parameters(model_fmu, info, runs: Runs, scoring: Scoring) -> list[Sensitivity]:
    """Every calibratable parameter, ranked by the share of the residual its sensitivity explains
    on the first SCREEN_SAMPLES samples of the first run (one simulation per parameter, plus one
    of the plain model)."""
    data, start_values = runs[0]
    screen = data.window(data.start, float(data.time[min(SCREEN_SAMPLES, data.time.size) - 1]))
    screen_runs = [(screen, start_values)]
    objective = Objective(model_fmu, screen_runs, scoring)
    errors = objective.errors({})
    if errors is None:
        raise FmuBuilderError(f"{model_fmu}: the plain model does not simulate over the training data; "
                              "check the data's start values")
    objective.units = relative_units(objective, errors)
    residual = errors / objective.units
    total = float(residual @ residual)
    if total == 0.0:
        return []          # the plain model fits the data exactly: nothing to explain
    ranked = []
    for position, var in enumerate(calibratable_parameters(info, set(start_values))):
        declared = float(var.start)
        delta = PERTURBATION * declared
        perturbed = objective.errors({var.name: declared + delta})
        if perturbed is None:
            continue
        gradient = (perturbed - residual) / delta
        gg = float(gradient @ gradient)
        if gg == 0.0:
            continue
        ranked.append(Sensitivity(var.name, declared, float(gradient @ residual) ** 2 / (gg * total), gradient,
                                  declared_at=position))
    return sorted(ranked, key=lambda s: s.explained, reverse=True)


def distinct(ranked: list[Sensitivity]) -> list[Sensitivity]:
    """The ranked parameters less those that act like a higher-ranked one: fitting both would give
    the same model twice. Of twins the one declared first in the model description is kept (the
    others recorded in its `equivalent`): twins explain the same share up to round-off, so the
    ranking between them is no choice."""
    kept = []
    for sensitivity in ranked:
        at = next((i for i, k in enumerate(kept) if k.acts_like(sensitivity)), None)
        if at is None:
            kept.append(sensitivity)
            continue
        first, second = sorted((kept[at], sensitivity), key=lambda s: s.declared_at)
        first.equivalent += [second.name] + second.equivalent
        second.equivalent = []
        kept[at] = first
    return kept


def fit_parameter(model_fmu, runs: Runs, scoring: Scoring, name: str, declared: float) -> Calibration | None:
    """Gauss-Newton on the score over `runs`, one sensitivity simulation per step, a step that
    does not lower the score halved, in at most FIT_SIMULATIONS simulations; None when the plain
    model does not simulate."""
    objective = Objective(model_fmu, runs, scoring)
    errors = objective.errors({name: declared})
    if errors is None:
        return None
    objective.units = relative_units(objective, errors)
    low, high = sorted((declared / RANGE, declared * RANGE))
    value, residual = declared, errors / objective.units
    score = float(residual @ residual)
    relative_delta = PERTURBATION
    while objective.simulations + 2 <= FIT_SIMULATIONS:
        delta = relative_delta * value
        perturbed = objective.errors({name: value + delta})
        if perturbed is None:
            break
        gradient = (perturbed - residual) / delta
        gg = float(gradient @ gradient)
        if gg == 0.0:
            break
        step = -float(gradient @ residual) / gg
        accepted = False
        while objective.simulations < FIT_SIMULATIONS and abs(step) > STEP_TOLERANCE * abs(value):
            trial_value = min(max(value + step, low), high)
            trial = objective.errors({name: trial_value})
            if trial is not None:
                trial_score = float(trial @ trial)
                if trial_score < score:
                    relative_delta = min(PERTURBATION, max(MIN_PERTURBATION, abs(trial_value - value) / abs(value)))
                    value, residual, score, accepted = trial_value, trial, trial_score, True
                    break
            step /= 2.0
        if not accepted or abs(step) <= STEP_TOLERANCE * abs(value):
            break
    return Calibration(name, declared, value, score, objective.simulations)


def calibrate(model_fmu, info, runs: Runs, scoring: Scoring, *,
              say=None) -> tuple[list[Sensitivity], list[Calibration]]:
    """Screen the parameters on the first run, fit the best MAX_CALIBRATED on all `runs`, less
    those that act like a higher-ranked one (the same model again: not fitted, none in their
    place). Returns the screening (all parameters, ranked) and the fits that lowered the training
    score."""
    say = say or (lambda *a, **k: None)
    ranked = screen_parameters(model_fmu, info, runs, scoring)
    fits = []
    leading = ranked[0].explained if ranked else 0.0
    chosen = [s for s in ranked if s.explained >= max(MIN_EXPLAINED, RUNNER_UP_SHARE * leading)]
    for sensitivity in distinct(chosen[:MAX_CALIBRATED]):
        same = (f"; {', '.join(sensitivity.equivalent)} acts alike and is not fitted apart"
                if sensitivity.equivalent else "")
        say(f"      calibrating {sensitivity.name} (explains {sensitivity.explained:.0%} of the residual "
            f"on the first {SCREEN_SAMPLES} samples{same}) ...")
        fit = fit_parameter(model_fmu, runs, scoring, sensitivity.name, sensitivity.declared)
        if fit is not None and fit.value != fit.declared:
            fits.append(fit)
    return ranked, fits

