"""Errors of a model (plain or hybrid FMU) against measured data, as the paper's table has them.

Every model is simulated the same way (engine, adaptive solver, the bench's sensor lag applied
to the model's signals), so "before" and "after" differ only in the model.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..diagnose.data import MeasuredData, load_measurement
from ..diagnose.runs import ModelRunner
from ..errors import FmuBuilderError
from ..fmi import read_model_info


@dataclass
class Evaluation:
    errors: dict                  # signal -> {"mse", "max_abs", "final"}
    time: np.ndarray
    predicted: dict               # signal -> model values at the data's time stamps
    wall_time: float


def load_data(path: Path, fmu_path: Path) -> MeasuredData:
    try:
        return load_measurement(path, read_model_info(fmu_path))
    except FmuBuilderError as exc:
        # Two data files per run: say which one is wrong.
        if path.name in str(exc):
            raise
        raise FmuBuilderError(f"{path}: {exc}") from None


def evaluate(fmu_path: Path, data: MeasuredData, start_values: dict) -> Evaluation:
    runner = ModelRunner(fmu_path, start_values=start_values, data_time=data.time,
                         start=float(data.time[0]), stop=float(data.time[-1]), measured=data.names,
                         recorded=[], sensor_lag=data.sensor_lag, fine_step=data.fine_step, rtol=1e-8)
    try:
        run = runner.simulate(trajectories=False)
    finally:
        runner.close()
    errors = {name: signal_errors(data.signals[name], run.predicted[name]) for name in data.names}
    return Evaluation(errors, runner.data_time, run.predicted, run.wall_time)


def signal_errors(measured: np.ndarray, model: np.ndarray) -> dict:
    error = np.asarray(model, dtype=float) - np.asarray(measured, dtype=float)
    return {"mse": float(np.mean(error ** 2)), "max_abs": float(np.max(np.abs(error))), "final": float(error[-1])}


def relative_mse(before: dict, after: dict) -> float:
    """Mean over signals of MSE after / MSE before: below 1 is better, one number to compare models."""
    ratios = [after[s]["mse"] / before[s]["mse"] for s in before if before[s]["mse"] > 0]
    return float(np.mean(ratios)) if ratios else 1.0
