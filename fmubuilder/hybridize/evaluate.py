"""Errors of a model (plain or hybrid FMU) against measured data, as the paper's table has them.

Every model is simulated the same way (`Scoring`: the engine with the solver and step the
NeuralFMU trains with, the bench's sensor lag applied to the model's signals), so "before" and
"after", and the candidates among themselves, differ only in the model.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..data import MeasuredData, first_order_lag, load_data
from ..errors import FmuBuilderError
from ..fmi import read_model_info


@dataclass(frozen=True)
class Scoring:
    """How every model is simulated for its errors: a fixed-step solver at `step` seconds, or with
    `rtol` an adaptive one recorded every `step` seconds (the sensor lag is applied on that grid)."""
    solver: str
    step: float
    rtol: float | None = None

    @classmethod
    def like_training(cls, info, data: MeasuredData) -> "Scoring":
        """The NeuralFMU's training solver and step (see neural.train.Trainer): explicit Euler at
        the FMU's DefaultExperiment step size."""
        step = info.default_experiment.step_size or (data.stop - data.start) / max(10 * data.time.size, 1000)
        return cls("euler", float(step))

    @classmethod
    def accurate(cls, step: float, rtol: float = 1e-7) -> "Scoring":
        """DOPRI5 at a tight tolerance: the model's own error, not the solver's."""
        return cls("dopri5", float(step), rtol)

    def describe(self) -> str:
        if self.rtol is not None:
            return f"engine {self.solver.upper()}, rtol {self.rtol:g}, recorded every {self.step:g} s"
        return f"engine {self.solver.capitalize()}, h = {self.step:g} s"


@dataclass
class Evaluation:
    errors: dict                  # signal -> {"mse", "max_abs", "final"}
    time: np.ndarray
    predicted: dict               # signal -> model values at the data's time stamps
    wall_time: float

    def on(self, data: MeasuredData, start: float, stop: float) -> "Evaluation":
        """The errors on the samples of [start, stop] only (of the same simulation)."""
        keep = (self.time >= start) & (self.time <= stop)
        predicted = {name: values[keep] for name, values in self.predicted.items()}
        errors = {name: signal_errors(data.signals[name][keep], predicted[name]) for name in data.names}
        return Evaluation(errors, self.time[keep], predicted, self.wall_time)


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
    import time as wallclock

    from ..simulation import simulate
    started = wallclock.perf_counter()
    inputs = {"time": data.time, **data.inputs} if data.inputs else None
    steps = {"step_size": scoring.step} if scoring.rtol is None else {"rtol": scoring.rtol}
    with np.errstate(all="ignore"):     # a poor candidate may run off; its errors say so
        result = simulate(fmu_path, start_time=data.start, stop_time=data.stop, start_values=start_values,
                          inputs=inputs, variables=data.names, solver=scoring.solver, output_interval=scoring.step,
                          record_events=True, **steps)
    predicted = {}
    for name in data.names:
        seen = first_order_lag(result.time, np.asarray(result[name], dtype=float), data.sensor_lag)
        predicted[name] = sample_settled(result.time, seen, data.time)
    errors = {name: signal_errors(data.signals[name], predicted[name]) for name in data.names}
    return Evaluation(errors, data.time, predicted, wallclock.perf_counter() - started)


def sample_settled(time: np.ndarray, values: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Values at the times `at`, linear between records; where two records share a time (before and
    after an event) a stamp there takes the value after it, as a logger sees the settled value."""
    index = np.clip(np.searchsorted(time, at, side="right") - 1, 0, len(time) - 2)
    t0, t1 = time[index], time[index + 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        fraction = np.where(t1 > t0, (at - t0) / (t1 - t0), 1.0)
    return values[index] + np.clip(fraction, 0.0, 1.0) * (values[index + 1] - values[index])


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
