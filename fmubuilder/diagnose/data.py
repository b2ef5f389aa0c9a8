"""Measured data as the diagnosis reads it: signals, their run-to-run spread and the bench.

The CSV follows the measurement convention of :mod:`fmubuilder.synth`: ``time`` first, one
column per signal named after an FMU variable, and optionally ``<signal>_std`` columns with
the spread over repeated runs. A sidecar ``<csv>.json`` (written by the generator or by hand)
may describe the bench; the diagnosis uses three of its entries because a model output is
only comparable with a measurement that went through the same sensor:

* ``bench.lag``: time constant of the first-order sensor filter [s] (default 0: no filter);
* ``bench.runs``: how many runs the ``_std`` spread was computed from (default 2);
* ``start_values``: start values the data were recorded with (e.g. the driving cycle).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import FmuBuilderError
from ..fmi.model import ModelInfo
from ..simulation.inputs import read_csv_signals
from ..synth import read_sidecar, split_uncertainty_columns

DEFAULT_RUNS = 2
MIN_SAMPLES = 8


@dataclass
class MeasuredData:
    path: Path
    time: np.ndarray
    signals: dict[str, np.ndarray]            # measured values, e.g. the mean over the runs
    spread: dict[str, np.ndarray]             # per-sample spread over the runs (`_std` columns)
    runs: int = DEFAULT_RUNS                  # runs behind the spread
    sensor_lag: float = 0.0                   # s, first-order sensor filter
    fine_step: float | None = None            # s, grid the bench simulated the truth on
    start_values: dict = field(default_factory=dict)

    @property
    def names(self) -> list[str]:
        return list(self.signals)


def load_measurement(path: str | Path, info: ModelInfo) -> MeasuredData:
    """Read a measurement CSV (and its sidecar) and check its signals against the model."""
    path = Path(path)
    time, columns = read_csv_signals(path)
    names, uncertainty = split_uncertainty_columns(list(columns))
    _check_signals(path, names, info)
    if len(time) < MIN_SAMPLES:
        raise FmuBuilderError(
            f"{path} has {len(time)} samples; the diagnosis needs at least {MIN_SAMPLES} to tell an effect from noise")
    sidecar = read_sidecar(path) or {}
    bench = sidecar.get("bench") or {}
    spread = {name: np.abs(columns[uncertainty[name]]) for name in names if name in uncertainty}
    return MeasuredData(
        path=path, time=time, signals={name: columns[name] for name in names}, spread=spread,
        runs=max(1, int(bench.get("runs", DEFAULT_RUNS))), sensor_lag=float(bench.get("lag", 0.0) or 0.0),
        fine_step=_positive_or_none(bench.get("fine_step")), start_values=dict(sidecar.get("start_values") or {}))


def _check_signals(path: Path, names: list[str], info: ModelInfo) -> None:
    if not names:
        raise FmuBuilderError(f"{path} has no signal columns; add columns named after FMU variables, e.g. time,speed")
    for name in names:
        var = info.variables.get(name)
        if var is None:
            info.variable(name)  # raises with the close names and how to list the variables
        if var.type != "Real":
            raise FmuBuilderError(
                f"{path}: column '{name}' is a {var.type} variable of the model; "
                "measured signals must be Real variables")


def _positive_or_none(value) -> float | None:
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number if number > 0 else None
