"""Measured data for training: a CSV with `time` first (strictly increasing, any spacing), then
columns named exactly as FMU variables.

Columns that are FMU inputs drive the FMU; the others (states, outputs, locals) are measured
signals compared with the simulation. A column `X_std` next to a column `X` is the uncertainty of X
(the convention of `fmubuilder synth`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import FmuBuilderError
from ..fmi import ModelInfo
from ..simulation.inputs import InputSignals, input_signals_from, read_csv_signals
from ..synth import split_uncertainty_columns


@dataclass
class MeasuredData:
    time: np.ndarray
    signals: dict[str, np.ndarray]                       # measured FMU variables
    std: dict[str, np.ndarray] = field(default_factory=dict)   # uncertainty of some signals
    inputs: dict[str, np.ndarray] = field(default_factory=dict)  # FMU inputs
    source: str = "data"

    @property
    def start(self) -> float:
        return float(self.time[0])

    @property
    def stop(self) -> float:
        return float(self.time[-1])

    def input_signals(self, info: ModelInfo) -> InputSignals | None:
        return input_signals_from({"time": self.time, **self.inputs}, info) if self.inputs else None

    def at(self, name: str, t) -> np.ndarray:
        return np.interp(t, self.time, self.signals[name])

    def weights(self, name: str) -> np.ndarray:
        """Per-sample weights from the uncertainty band (mean 1), or ones without one."""
        if name not in self.std:
            return np.ones_like(self.time)
        variance = np.asarray(self.std[name], dtype=float) ** 2
        floor = 0.1 * float(np.mean(variance)) if np.any(variance > 0) else 1.0
        inverse = 1.0 / (variance + floor)
        return inverse / inverse.mean()


def load_data(path: str | Path, info: ModelInfo) -> MeasuredData:
    """Read and check a data CSV against the FMU's variables."""
    path = Path(path)
    time, columns = read_csv_signals(path)
    if time.size < 2:
        raise FmuBuilderError(f"{path} has {time.size} row(s); training data need at least two time stamps")
    names, uncertainty = split_uncertainty_columns(["time", *columns])
    signals, inputs = {}, {}
    for name in names:
        var = info.variable(name)
        if var.type != "Real":
            raise FmuBuilderError(f"{path}: column '{name}' is a {var.type} variable; measured signals must be Real")
        if var.causality == "input":
            inputs[name] = columns[name]
        elif var.is_parameter:
            raise FmuBuilderError(f"{path}: column '{name}' is a parameter; give parameters with --start {name}=VALUE")
        else:
            signals[name] = columns[name]
        if not np.all(np.isfinite(columns[name])):
            raise FmuBuilderError(f"{path}: column '{name}' holds non-finite values; remove or fill them")
    if not signals:
        raise FmuBuilderError(f"{path} has no measured signal: add columns named after FMU states or outputs")
    std = {name: columns[column] for name, column in uncertainty.items() if name in signals}
    return MeasuredData(time, signals, std, inputs, source=str(path))
