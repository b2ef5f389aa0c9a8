"""Errors of a model (plain or hybrid FMU) against measured data, every model simulated the same
way (`Scoring`, the bench's sensor lag applied), so that the candidates differ only in the model
(docs/ARCHITECTURE.md, "How a model is scored against data").
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..data import MeasuredData, load_data, sensor_reading
from ..errors import FmuBuilderError

# Scoring.checked's step search (see there).
FIRST_STEP_SHARE = 0.1
STEP_TOLERANCE = 0.1
MAX_HALVINGS = 4


@dataclass(frozen=True)
class Scoring:
    """How every model is simulated for its errors: a fixed-step solver at `step` seconds.
    `check`: largest mean square difference between h and h/2 over a signal's noise variance, from
    `checked` (None: the step was not checked). With `rtol`, an adaptive solver recorded every `step`
    seconds (the sensor lag is applied on that grid)."""
    solver: str
    step: float
    check: float | None = None
    halvings: int = 0
    rtol: float | None = None

    @classmethod
    def fmu_step(cls, info, data: MeasuredData) -> "Scoring":
        """Explicit Euler at the FMU's DefaultExperiment step size: cheap, unchecked (its error can
        exceed the noise; `checked` is what the workflow uses)."""
        step = info.default_experiment.step_size or (data.stop - data.start) / max(10 * data.time.size, 1000)
        return cls("euler", float(step))

    @classmethod
    def accurate(cls, step: float, rtol: float = 1e-7) -> "Scoring":
        """DOPRI5 at a tight tolerance: the model's own error, not the solver's."""
        return cls("dopri5", float(step), rtol=rtol)

    @classmethod
    def checked(cls, fmu_path: Path, data: MeasuredData, start_values: dict) -> "Scoring":
        """Classical RK4 at a step checked on the plain model over `data` (the training samples):
        start at FIRST_STEP_SHARE of the sample period, halve while h and h/2 differ by more than
        STEP_TOLERANCE of some signal's noise variance (`MeasuredData.noise_variance`), at most
        MAX_HALVINGS times. Without a spread in the data the noise is unknown: the first step, unchecked."""
        noise = {name: data.noise_variance(name) for name in data.names}
        noise = {name: value for name, value in noise.items() if value is not None and value > 0}
        step = first_step(data)
        if not noise:
            return cls("rk4", step)
        coarse = evaluate(fmu_path, data, start_values, cls("rk4", step))
        for halvings in range(MAX_HALVINGS + 1):
            fine = evaluate(fmu_path, data, start_values, cls("rk4", step / 2))
            ratio = max(float(np.mean((coarse.predicted[name] - fine.predicted[name]) ** 2)) / variance
                        for name, variance in noise.items())
            if ratio <= STEP_TOLERANCE or halvings == MAX_HALVINGS:    # nan (a run-off) halves too
                return cls("rk4", step, ratio, halvings)
            step, coarse = step / 2, fine
        raise AssertionError("unreachable")

    def describe(self) -> str:
        if self.rtol is not None:
            return f"engine {self.solver.upper()}, rtol {self.rtol:g}, recorded every {self.step:g} s"
        text = f"engine {self.solver.upper() if self.solver == 'rk4' else self.solver.capitalize()}, h = {self.step:g} s"
        if self.check is None:
            return text
        if self.check <= STEP_TOLERANCE:
            return text + f" (checked: h/2 differs by < {STEP_TOLERANCE:g} noise)"
        return text + (f" (checked: h/2 still differs by {self.check:.2g} noise after {self.halvings} halvings, "
                       "the most allowed)")


def first_step(data: MeasuredData) -> float:
    """FIRST_STEP_SHARE of the mean sample period, rounded down to 1, 2 or 5 x 10^n seconds (within
    2 %: jittered stamps at 10 Hz have a period a hair below 0.1 s, which is meant as 0.1 s)."""
    period = (data.stop - data.start) / (data.time.size - 1) if data.time.size > 1 else 1.0
    target = FIRST_STEP_SHARE * period * 1.02
    decade = 10.0 ** math.floor(math.log10(target))
    mantissa = next(m for m in (5.0, 2.0, 1.0) if m * decade <= target)
    return float(f"{mantissa * decade:.12g}")


@dataclass
class Evaluation:
    errors: dict                  # signal -> {"mse", "max_abs", "final"}
    time: np.ndarray
    predicted: dict               # signal -> model values at the data's time stamps


def read_data(path: Path, info) -> MeasuredData:
    """The data file, with its name in every complaint (the workflow reads several)."""
    try:
        return load_data(path, info)
    except FmuBuilderError as exc:
        if Path(path).name in str(exc):
            raise
        raise FmuBuilderError(f"{path}: {exc}") from None


def evaluate(fmu_path: Path, data: MeasuredData, start_values: dict, scoring: Scoring) -> Evaluation:
    """Simulate the FMU over the data's span and compare it, seen through the sensors, with the data."""
    result = simulate_over(fmu_path, data, start_values, data.names, scoring)
    predicted = {name: sensor_reading(result.time, result[name], data.time, data.sensor_lag) for name in data.names}
    with np.errstate(all="ignore"):
        errors = {name: signal_errors(data.signals[name], predicted[name]) for name in data.names}
    return Evaluation(errors, data.time, predicted)


def simulate_over(fmu_path: Path, data: MeasuredData, start_values: dict, names, scoring: Scoring, *,
                  output_interval: float | None = None, record_events: bool = True):
    """The FMU over the data's span with the data's inputs, by the engine as `scoring` says,
    recorded every `output_interval` (the scoring step) and, with `record_events`, on both sides of events."""
    from ..simulation import simulate
    inputs = {"time": data.time, **data.inputs} if data.inputs else None
    steps = {"step_size": scoring.step} if scoring.rtol is None else {"rtol": scoring.rtol}
    with np.errstate(all="ignore"):     # a poor candidate may run off; its errors say so
        return simulate(fmu_path, start_time=data.start, stop_time=data.stop, start_values=start_values,
                        inputs=inputs, variables=list(names), solver=scoring.solver,
                        output_interval=output_interval or scoring.step, record_events=record_events, **steps)


Runs = list[tuple[MeasuredData, dict]]      # data and the start values of their run


class Objective:
    """The errors of an FMU on some runs, given start values on top of each run's, and the
    simulations spent on them. The errors are stacked run by run, each run's signals in the data's
    order, every sample divided by `units` (of that layout; None: 1). One simulation is one pass
    over all the runs; a pass that fails (a run does not simulate, or its errors are not finite)
    costs one as well: it was work done. `bar`, when set, advances once a pass."""

    def __init__(self, fmu_path, runs: Runs, scoring: Scoring):
        self.fmu_path, self.runs, self.scoring = fmu_path, runs, scoring
        self.units: np.ndarray | None = None
        self.simulations = 0
        self.bar = None

    def errors(self, start_values: dict) -> np.ndarray | None:
        """(model - measured) / units of every signal on every run; None where a run fails."""
        self.simulations += 1
        try:
            pieces = []
            for data, run_start_values in self.runs:
                try:
                    run = evaluate(self.fmu_path, data, {**run_start_values, **start_values}, self.scoring)
                except FmuBuilderError:
                    return None
                pieces += [run.predicted[name] - data.signals[name] for name in data.names]
            errors = np.concatenate(pieces) if self.units is None else np.concatenate(pieces) / self.units
            return errors if np.all(np.isfinite(errors)) else None
        finally:
            if self.bar is not None:
                self.bar.advance()

    def per_signal(self, value_of) -> np.ndarray:
        """A vector of the errors' layout that holds value_of(data, name) for every sample of that signal."""
        return np.concatenate([np.full(data.signals[name].size, value_of(data, name))
                               for data, _ in self.runs for name in data.names])


def signal_errors(measured: np.ndarray, model: np.ndarray) -> dict:
    error = np.asarray(model, dtype=float) - np.asarray(measured, dtype=float)
    if error.size == 0:
        return {"mse": float("nan"), "max_abs": float("nan"), "final": float("nan")}
    return {"mse": float(np.mean(error ** 2)), "max_abs": float(np.max(np.abs(error))), "final": float(error[-1])}


def relative_mse(before: dict, after: dict) -> float:
    """Mean over signals of MSE after / MSE before: below 1 is better, one number to compare models."""
    ratios = [after[s]["mse"] / before[s]["mse"] for s in before if before[s]["mse"] > 0]
    if any(not np.isfinite(r) for r in ratios):
        return float("inf")
    return float(np.mean(ratios)) if ratios else 1.0
