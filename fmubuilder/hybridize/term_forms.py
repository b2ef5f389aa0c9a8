"""The fitted term's form, chosen on the validation data among the forms of the diagnosis' leading
variables, each fitted through the simulation of the training runs.

The diagnosis ranks forms by a regression on closed-loop responses linearised around the plain model
over its traced window (the first samples of the training run). Forms of one variable that differ
over the whole run explain nearly alike there: on the VLDM's extra resistance, `c1 v + c2 v|v|`,
the diagnosis' window explains 0.983 of the residual with `v` alone, 0.982 with `v|v|` alone and
offers a third variable (`motor_torque_limit`, a function of the speed on this car) that fits
slightly better there and far worse beyond. So per leading variable its best form alone and its two
best forms together are fitted, their coefficients through the simulation of every training run
(Levenberg-Marquardt on one scale per form, refine_term's search, here through the engine with the
term as a NeuralFMU's base term and no ANN), and scored on the validation data. The diagnosis' own
term stays unless another form's validation score is lower by the noise margin (choice.py, the rule
the candidates follow): first the forms with one coefficient, then those with two (choose_form).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..errors import FmuBuilderError
from ..progress import progress

# Leading variables (the diagnosis' ranking, in its channel) whose forms are tried.
FORM_VARIABLES = 2
# Simulations of the training runs per form (refine_term's budget for its scale).
SIMULATIONS_PER_FORM = 10


@dataclass
class FormFit:
    """One form of the term, its coefficients fitted on the training runs, scored on validation."""
    label: str
    terms: list[dict]             # base-term dicts (base_term.py) with the fitted coefficients
    start: list[float]            # the coefficients it started from (the diagnosis')
    training_objective: float     # mean squared residual in noise units, after the fit
    validation_score: float       # score.validation_score on the validation parts
    simulations: int

    def to_dict(self) -> dict:
        return {"form": self.label, "coefficients": [t["coefficient"] for t in self.terms], "start": self.start,
                "training_objective": _finite(self.training_objective),
                "validation_score": _finite(self.validation_score), "simulations": self.simulations}


def candidate_forms(diagnosis) -> dict[str, list[dict]]:
    """label -> terms to fit: the diagnosis' own term, and per leading variable its best form and its
    two best forms together (the second at half of each coefficient: together they start near the
    first's size). Variables an FMU cannot read (time) and constant terms are left out."""
    from .term_started import fmu_term_inputs
    fitted = diagnosis.fitted_term
    forms = {}
    if fitted and fmu_term_inputs(fitted["terms"]) and all(t["basis"] != "1" for t in fitted["terms"]):
        forms[label_of(fitted["terms"])] = [dict(t) for t in fitted["terms"]]
    # generic shapes (a constant, a ramp in time: no variable) are not forms of a variable
    ranked = [c for c in diagnosis.candidates
              if c.channel == diagnosis.channel and c.inputs and c.inputs[0] not in (None, "time")]
    for variable in list(dict.fromkeys(c.inputs[0] for c in ranked))[:FORM_VARIABLES]:
        own = [term_of(c) for c in ranked if c.inputs[0] == variable]
        forms.setdefault(own[0]["form"], own[:1])
        if len(own) > 1:
            forms.setdefault(label_of(own[:2]), [{**t, "coefficient": t["coefficient"] / 2} for t in own[:2]])
    return forms


def label_of(terms: list[dict]) -> str:
    """A form's name: its terms' forms, e.g. 'speed + speed*|speed|'."""
    return " + ".join(t["form"] for t in terms)


def term_of(candidate) -> dict:
    """A diagnosis candidate (one form of one variable, e.g. '(v - 128)*|v - 128|') as a base term."""
    return {"variable": candidate.inputs[0], "basis": candidate.basis, "center": candidate.center,
            "coefficient": float(candidate.coefficient), "form": candidate.form}


class TermObjective:
    """refine_term's objective for a term as a NeuralFMU's base term: `errors({label: scale})` scales
    each form's coefficient and returns the residuals of every training run in noise units (None
    where a run fails), one simulation each call."""

    def __init__(self, model_fmu, channel: str, terms: list[dict], runs, scoring, units_of, aliases: dict):
        from ..neural import NeuralFMU, TopologyConfig
        inputs = list(dict.fromkeys(t["variable"] for t in terms))
        self.model = NeuralFMU(model_fmu, TopologyConfig(channels=[channel], inputs=inputs, kind="residual",
                                                         base_terms=terms))
        self.weights = self.model.topology.base.weights.clone()
        self.runs, self.scoring, self.aliases = runs, scoring, aliases
        self.units = np.concatenate([np.full(data.signals[name].size, units_of(data, name))
                                     for data, _ in runs for name in data.names])
        self.labels = [f"form {k}" for k in range(len(terms))]
        self.simulations = 0
        self.bar = None

    def set_scales(self, scales) -> None:
        with torch.no_grad():
            per_form = torch.tensor(scales, dtype=self.weights.dtype)[None, :, None]   # weights: [basis, form, 1]
            self.model.topology.base.weights.copy_(self.weights * per_form)

    def errors(self, values: dict) -> np.ndarray | None:
        self.simulations += 1
        self.set_scales([values[label] for label in self.labels])
        try:
            pieces = []
            for data, start_values in self.runs:
                predicted = self.predicted(data, data, start_values)
                if predicted is None:
                    return None
                pieces += [predicted[name] - data.signals[name] for name in data.names]
            errors = np.concatenate(pieces) / self.units
            return errors if np.all(np.isfinite(errors)) else None
        finally:
            if self.bar is not None:
                self.bar.advance()

    def predicted(self, run_data, data, start_values: dict) -> dict | None:
        """The signals at `data`'s samples (seen through its sensors) of a simulation over `run_data`."""
        from ..neural.train import predicted_at_samples, simulate_over
        try:
            with np.errstate(all="ignore"):
                run = simulate_over(self.model, run_data, self.scoring.step, self.scoring.solver, start_values,
                                    aliases=self.aliases)
        except FmuBuilderError:
            return None
        if run.terminated_early:
            return None
        return {name: predicted_at_samples(data, run, name, data.sensor_lag, self.aliases) for name in data.names}

    def close(self) -> None:
        self.model.close()


def fit_forms(model_fmu, channel: str, forms: dict[str, list[dict]], train_runs, validation_parts, scoring,
              noise: dict[str, float], aliases: dict, *, show: bool = True) -> list[FormFit]:
    """Each form's coefficients fitted on the training runs (data, start values), then scored on the
    validation parts (whole run simulated, its window scored)."""
    from ..score import validation_score
    from .refine_term import levenberg_marquardt, noise_level
    fits = []
    per_form = SIMULATIONS_PER_FORM + 1         # the fit's, then one over the validation parts
    with progress(per_form * len(forms), "fitting the term's forms through the simulation", "simulation",
                  show=show) as bar:
        for label, terms in forms.items():
            try:
                objective = TermObjective(model_fmu, channel, terms, train_runs, scoring,
                                          lambda data, name: noise_level(noise, name, data), aliases)
            except FmuBuilderError:     # a form a NeuralFMU cannot hold: it does not simulate
                bar.advance(per_form)
                fits.append(FormFit(label, terms, [float(t["coefficient"]) for t in terms], math.inf, math.inf, 0))
                continue
            objective.bar = bar
            try:
                start = np.ones(len(terms))
                residual = objective.errors(dict(zip(objective.labels, start)))
                scales, cost = start, math.inf
                if residual is not None:
                    scales, cost, _ = levenberg_marquardt(objective, objective.labels, start, residual,
                                                          SIMULATIONS_PER_FORM)
                objective.set_scales(scales)
                bar.advance(SIMULATIONS_PER_FORM - objective.simulations)
                fitted = [{**t, "coefficient": float(t["coefficient"] * s)} for t, s in zip(terms, scales)]
                score = _validation(objective, validation_parts, validation_score) if math.isfinite(cost) else math.inf
                bar.advance()
                fits.append(FormFit(label, fitted, [float(t["coefficient"]) for t in terms], cost, score,
                                    objective.simulations))
            finally:
                objective.close()
    return fits


def _validation(objective: TermObjective, parts, validation_score) -> float:
    """Geometric mean over the signals of MSE / noise variance on every validation part."""
    squared = {}
    objective.simulations += 1
    for part in parts:
        data = part.samples()
        predicted = objective.predicted(part.data, data, part.start_values)
        if predicted is None:
            return math.inf
        for name in data.names:
            squared.setdefault(name, []).append((predicted[name] - data.signals[name]) ** 2)
    errors = {name: {"mse": float(np.mean(np.concatenate(pieces)))} for name, pieces in squared.items()}
    floors = {}
    for name in errors:
        variance = parts[0].data.noise_variance(name)
        floors[name] = variance if variance is not None and variance > 0 else 1.0   # the same for every form
    return validation_score(errors, floors)


def choose_form(fits: list[FormFit], margin: float) -> FormFit | None:
    """The first fit (the diagnosis' own term, where an FMU can read it) unless a form beats it on the
    validation score by the noise margin: first the best form with one coefficient, then, against the
    one kept, the best with two; None when no form simulates. A short validation tail cannot tell
    forms apart by less: the DC drive's extra heating (tests/hybridize/test_hybridize.py) scores its
    true form current*|current| 18.4 and power*|power| 12.4 on 3 s of validation with a margin of
    x3.2, while their training objectives are 0.61 and 138."""
    chosen = fits[0] if fits else None
    for size in sorted({len(f.terms) for f in fits}):
        own_size = [f for f in fits[1:] if len(f.terms) == size and math.isfinite(f.validation_score)]
        if not own_size:
            continue
        best = min(own_size, key=lambda f: f.validation_score)
        if not math.isfinite(chosen.validation_score) or best.validation_score * margin < chosen.validation_score:
            chosen = best
    return chosen if chosen is not None and math.isfinite(chosen.validation_score) else None


def fitted_term_of(fitted: dict, terms: list[dict]) -> dict:
    """The diagnosis' fitted term (dict) with other terms, its expression rewritten; what the
    diagnosis measured of its own term (explained variances, p-value) stays with the diagnosis."""
    from .refine_term import scaled_term
    own = {"channel": fitted["channel"], "terms": terms, "offered": fitted.get("offered", True),
           "diagnosed": fitted["expression"]}
    return scaled_term(own, 1.0)


def _finite(value: float) -> float | None:
    return value if math.isfinite(value) else None
