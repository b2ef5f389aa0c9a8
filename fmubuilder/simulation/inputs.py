"""Time signals from CSV files, and FMU inputs interpolated from them.

A signal CSV has a header row whose first column is `time` and whose other columns are
named after variables; every later row is one sample. Bad files fail with one line naming
the file, row and column. Inputs are piecewise linear between samples and held constant
outside them; a sample time is a kink of the input, so the simulator restarts its solver
there (time stamps must be strictly increasing: a jump needs two distinct times).
"""
from __future__ import annotations

import bisect
import csv
import math
from pathlib import Path
from typing import Mapping

import numpy as np

from ..errors import FmuBuilderError
from ..fmi.model import ModelInfo, Variable


def read_csv_signals(path: str | Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Read a CSV of sampled signals: returns (time, {column name: values})."""
    path = Path(path)
    header, rows = _read_rows(path)
    columns = _parse_columns(path, header, rows)
    time = columns.pop("time")
    _check_increasing(path, time, [f"row {number}" for number, _ in rows])
    return time, columns


def _read_rows(path: Path) -> tuple[list[str], list[tuple[int, list[str]]]]:
    try:
        with open(path, newline="", encoding="utf-8-sig") as file:
            lines = [(number, row) for number, row in enumerate(csv.reader(file), start=1)
                     if any(cell.strip() for cell in row)]
    except FileNotFoundError:
        raise FmuBuilderError(f"{path}: no such file; give the path of a CSV file") from None
    except IsADirectoryError:
        raise FmuBuilderError(f"{path} is a directory; give the path of a CSV file") from None
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise FmuBuilderError(f"{path}: cannot read it as a CSV text file ({exc})") from None
    if not lines:
        raise FmuBuilderError(f"{path} is empty; it needs a header row starting with 'time' and data rows")
    header = [cell.strip() for cell in lines[0][1]]
    if header[0] != "time":
        raise FmuBuilderError(
            f"{path}, row {lines[0][0]}: the first column is '{header[0]}', it must be 'time' "
            "(a header row: time,<signal>,...)")
    for i, name in enumerate(header):
        if not name:
            raise FmuBuilderError(
                f"{path}, row {lines[0][0]}: column {i + 1} has an empty name; name every column")
        if name in header[:i]:
            raise FmuBuilderError(
                f"{path}, row {lines[0][0]}: column '{name}' appears twice; column names must be unique")
    if len(lines) < 2:
        raise FmuBuilderError(f"{path} has a header but no data rows; add at least one sample")
    for number, row in lines[1:]:
        if len(row) != len(header):
            raise FmuBuilderError(
                f"{path}, row {number}: {len(row)} values for {len(header)} columns; "
                "every row needs one value per column")
    return header, lines[1:]


def _parse_columns(path: Path, header: list[str], rows) -> dict[str, np.ndarray]:
    columns = {}
    for j, name in enumerate(header):
        cells = [row[j] for _, row in rows]
        try:
            values = np.array(cells, dtype=float)
        except ValueError:
            values = None
        if values is None or not np.all(np.isfinite(values)):
            _raise_bad_cell(path, name, cells, rows)
        columns[name] = values
    return columns


def _raise_bad_cell(path: Path, name: str, cells: list[str], rows) -> None:
    for cell, (number, _) in zip(cells, rows):
        try:
            value = float(cell)
        except ValueError:
            raise FmuBuilderError(
                f"{path}, row {number}, column '{name}': '{cell.strip()}' is not a number; "
                "give a decimal number") from None
        if not math.isfinite(value):
            raise FmuBuilderError(
                f"{path}, row {number}, column '{name}': '{cell.strip()}' is not a finite number; "
                "fill in the missing sample or drop the row")


def _check_increasing(source: Path | str, time: np.ndarray, row_labels: list[str]) -> None:
    bad = np.flatnonzero(np.diff(time) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise FmuBuilderError(
            f"{source}, {row_labels[i]}: time {float(time[i])!r} does not increase from the previous "
            f"{float(time[i - 1])!r}; "
            "time stamps must be strictly increasing (a jump needs two distinct times)")


class InputSignals:
    """FMU inputs sampled at common times, each mapped to its variable.

    Real continuous inputs are interpolated linearly (`at(t)`); discrete inputs (Integer,
    Boolean, or Real with discrete variability) hold their last sample and may only change
    at events, so their change times are reported by `discrete_change_times`.
    """

    def __init__(self, time, values: Mapping[str, np.ndarray], variables: list[Variable]):
        self.time = np.asarray(time, dtype=float)
        by_name = {v.name: v for v in variables}
        self.continuous = [by_name[n] for n in values if _is_continuous(by_name[n])]
        self.discrete = [by_name[n] for n in values if not _is_continuous(by_name[n])]
        self._times = self.time.tolist()
        cont = np.zeros((self.time.size, len(self.continuous)))     # (samples, continuous inputs)
        for k, var in enumerate(self.continuous):
            cont[:, k] = values[var.name]
        self._cont = cont
        dt = np.diff(self.time)
        self._slope = np.diff(cont, axis=0) / dt[:, None] if len(self._times) > 1 else np.zeros((0, cont.shape[1]))
        self._disc = {v.name: np.asarray(values[v.name]) for v in self.discrete}
        self._segment = 0

    @property
    def names(self) -> list[str]:
        """The input variables' names, continuous ones first."""
        return [v.name for v in self.continuous + self.discrete]

    @property
    def breakpoints(self) -> np.ndarray:
        """Sample times of continuous inputs: their derivative jumps there."""
        return self.time if self.continuous else np.zeros(0)

    def at(self, t: float) -> np.ndarray:
        """Values of the continuous inputs at t (linear, constant outside the samples)."""
        times = self._times
        i = self._segment
        if not (times[i] <= t < times[i + 1] if i + 1 < len(times) else False):
            if t <= times[0]:
                return self._cont[0]
            if t >= times[-1]:
                return self._cont[-1]
            i = self._segment = bisect.bisect_right(times, t) - 1
        return self._cont[i] + (t - times[i]) * self._slope[i]

    def table(self, times) -> np.ndarray:
        """Values of the continuous inputs at several times: [len(times), continuous inputs]."""
        times = np.atleast_1d(np.asarray(times, dtype=float))
        out = np.empty((times.size, len(self.continuous)))
        for k in range(len(self.continuous)):
            out[:, k] = np.interp(times, self.time, self._cont[:, k])
        return out

    def tables(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(continuous values [samples, continuous inputs], their slopes [samples - 1, continuous
        inputs], discrete values [samples, discrete inputs] as floats): what `at` and
        `discrete_at` read, for the compiled loop."""
        discrete = np.zeros((self.time.size, len(self.discrete)))
        for k, var in enumerate(self.discrete):
            discrete[:, k] = self._disc[var.name]
        return self._cont, self._slope, discrete

    def discrete_at(self, t: float) -> dict[str, object]:
        """Values of the discrete inputs at t (the last sample at or before t)."""
        i = max(bisect.bisect_right(self._times, t) - 1, 0)
        return {name: values[i].item() for name, values in self._disc.items()}

    def discrete_change_times(self) -> np.ndarray:
        """Times at which some discrete input takes a new value."""
        if not self._disc or self.time.size < 2:
            return np.zeros(0)
        changed = np.zeros(self.time.size - 1, dtype=bool)
        for values in self._disc.values():
            changed |= values[1:] != values[:-1]
        return self.time[1:][changed]


def _is_continuous(var: Variable) -> bool:
    return var.type == "Real" and var.variability == "continuous"


def check_input_names(names, info: ModelInfo, source: str) -> list[Variable]:
    """The input variables for signal names; unknown names fail listing the model's inputs."""
    inputs = {v.name: v for v in info.inputs}
    unknown = [n for n in names if n not in inputs]
    if unknown:
        have = ", ".join(inputs) if inputs else "none"
        verb = "is not an input" if len(unknown) == 1 else "are not inputs"
        raise FmuBuilderError(
            f"{source}: {', '.join(repr(n) for n in unknown)} {verb} of '{info.model_name}' "
            f"(its inputs: {have}); rename or drop the column")
    return [inputs[n] for n in names]


def load_input_csv(path: str | Path, info: ModelInfo) -> InputSignals:
    """Read an input CSV and check its columns against the model's inputs."""
    time, columns = read_csv_signals(path)
    variables = check_input_names(list(columns), info, str(path))
    _check_discrete_values(str(path), columns, variables)
    return InputSignals(time, columns, variables)


def input_signals_from(data, info: ModelInfo) -> InputSignals:
    """Inputs given in memory: a mapping {'time': t, name: values, ...} or a numpy
    structured array whose first field is the time."""
    if isinstance(data, np.ndarray) and data.dtype.names:
        names = list(data.dtype.names)
        mapping = {name: data[name] for name in names}
        time_name = names[0]
    elif isinstance(data, Mapping):
        mapping = dict(data)
        time_name = "time"
        if time_name not in mapping:
            raise FmuBuilderError("inputs: no 'time' entry; give {'time': [...], '<input>': [...]}")
    else:
        raise FmuBuilderError("inputs must be a dict {'time': [...], '<input>': [...]} or a structured numpy array")
    try:
        time = np.asarray(mapping.pop(time_name), dtype=float).ravel()
        columns = {name: np.asarray(v, dtype=float).ravel() for name, v in mapping.items()}
    except (TypeError, ValueError):
        raise FmuBuilderError("inputs: every signal must be a sequence of numbers") from None
    if time.size == 0:
        raise FmuBuilderError("inputs: the time array is empty; give at least one sample")
    for name, values in [("time", time), *columns.items()]:
        if values.size != time.size:
            raise FmuBuilderError(
                f"inputs: '{name}' has {values.size} samples but time has {time.size}; give one per time")
        if not np.all(np.isfinite(values)):
            row = int(np.flatnonzero(~np.isfinite(values))[0])
            raise FmuBuilderError(f"inputs: '{name}' sample {row} is not a finite number")
    _check_increasing("inputs", time, [f"sample {i}" for i in range(time.size)])
    variables = check_input_names(list(columns), info, "inputs")
    _check_discrete_values("inputs", columns, variables)
    return InputSignals(time, columns, variables)


def _check_discrete_values(source: str, columns, variables: list[Variable]) -> None:
    for var in variables:
        if var.api_type in ("Integer", "Boolean"):
            values = columns[var.name]
            bad = np.flatnonzero(values != np.round(values))
            if var.api_type == "Boolean":
                bad = np.flatnonzero((values != 0) & (values != 1))
            if bad.size:
                raise FmuBuilderError(
                    f"{source}: input '{var.name}' is {var.type} but sample {int(bad[0])} is {values[bad[0]]:g}; "
                    f"give {'0 or 1' if var.api_type == 'Boolean' else 'whole numbers'}")
