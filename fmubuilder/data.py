"""Measured data, as every stage reads it: the CSV, its sidecar and the sensor model.

A data CSV has ``time`` first (seconds, strictly increasing, any spacing), then columns named
exactly as FMU variables. Columns that are FMU inputs drive the FMU; the others (states, outputs,
locals) are measured signals compared with the simulation. A column ``X_std`` next to ``X`` is
the run-to-run spread of X.

A sidecar ``<csv>.json`` (written by ``fmubuilder synth``, or by hand) describes the data set:

* ``start_values``: start values the data were recorded with (e.g. the driving cycle); they
  belong to the data set, since a cycle or an operating point is often a model parameter;
* ``sensor_lag`` (or ``bench.lag``): time constant of the sensors' first-order lag [s];
  a model output is comparable with a measurement only after the same filter (default 0);
* ``bench.runs``: how many runs the ``_std`` spread comes from (default 2);
* ``bench.fine_step``: the grid the bench simulated the truth on [s] (optional).
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Sequence

import numpy as np

from .errors import FmuBuilderError

UNCERTAINTY_SUFFIX = "_std"
DEFAULT_RUNS = 2
# A simulation started at a measured time (MeasuredData.start_estimate): the line through the first
# START_SAMPLES samples (as many as the diagnosis' start estimate), at most START_SECONDS of them
# (few: a state soon changes its course, and a line through a curve misses its start), and the
# model's own value kept while it lies within START_AGREEMENT standard errors of that line's value.
START_SAMPLES = 5
START_SECONDS = 1.0
START_AGREEMENT = 3.0


@dataclass
class MeasuredData:
    time: np.ndarray
    signals: dict[str, np.ndarray]                               # measured FMU variables
    std: dict[str, np.ndarray] = field(default_factory=dict)     # run-to-run spread of some signals
    inputs: dict[str, np.ndarray] = field(default_factory=dict)  # FMU inputs
    source: str = "data"                                         # where the data came from, for messages
    sensor_lag: float = 0.0                                      # s, first-order sensor filter
    runs: int = DEFAULT_RUNS                                     # runs behind the spread
    fine_step: float | None = None                               # s, grid the bench simulated on
    start_values: dict = field(default_factory=dict)             # from the sidecar
    path: Path | None = None
    # Noise variance of the measured value of signals without a spread column, estimated from the
    # data (the significance test's noise fit of the declared model's residual); set by the caller.
    noise_estimate: dict = field(default_factory=dict)

    @property
    def names(self) -> list[str]:
        return list(self.signals)

    @property
    def start(self) -> float:
        return float(self.time[0])

    @property
    def stop(self) -> float:
        return float(self.time[-1])

    def input_signals(self, info):
        """The FMU inputs (an `InputSignals` for the FMU described by `info`), or None."""
        if not self.inputs:
            return None
        from .simulation.inputs import input_signals_from
        return input_signals_from({"time": self.time, **self.inputs}, info)

    def weights(self, name: str) -> np.ndarray:
        """Per-sample weights from the spread (mean 1), or ones without one."""
        if name not in self.std:
            return np.ones_like(self.time)
        variance = np.asarray(self.std[name], dtype=float) ** 2
        floor = 0.1 * float(np.mean(variance)) if np.any(variance > 0) else 1.0
        inverse = 1.0 / (variance + floor)
        return inverse / inverse.mean()

    def noise_variance(self, name: str) -> float | None:
        """Noise variance of the measured value (the mean over the runs): the spread's mean square
        over the runs, as the significance test takes it; without a spread column the estimate from
        the data (noise_estimate), else None."""
        if name not in self.std or not np.size(self.std[name]):
            return self.noise_estimate.get(name)
        return float(np.mean(np.asarray(self.std[name], dtype=float) ** 2)) / self.runs

    def start_estimate(self, name: str, t0: float, model_value: float | None = None, model_run=None) -> float:
        """The value of signal `name` to start a simulation with at t0: `model_value` if the first
        samples from t0 agree with it (within START_AGREEMENT standard errors of a line fitted
        through them), else that line's value at t0: a single sample carries its full noise.
        `model_run` (times -> the model's values there, model_value at t0) is the course the model
        takes from there: the line is fitted through the data minus the run's change, so that a
        signal curving within the samples, as the model's run does, is not taken for a start apart
        from the model's (the VLDM's speed, braking to a halt within the first half second after
        900 s: a line through its samples put the start 3.4 noise standard deviations low, and the
        driver's controller answered with a spike of 10 kW on the power)."""
        first = int(np.searchsorted(self.time, t0 - 1e-9 * max(1.0, abs(t0))))
        last = min(first + START_SAMPLES, int(np.searchsorted(self.time, t0 + START_SECONDS, side="right")))
        t, y = self.time[first:last] - t0, np.asarray(self.signals[name][first:last], dtype=float)
        if model_run is not None and model_value is not None:
            y = y - (np.asarray(model_run(self.time[first:last]), dtype=float) - float(model_value))
        if t.size < 3:
            fitted, error = float(np.interp(t0, self.time, self.signals[name])), math.inf
        else:
            fitted, error = _intercept(t, y, self.noise_variance(name))
        if model_value is not None and abs(float(model_value) - fitted) <= START_AGREEMENT * error:
            return float(model_value)
        return fitted

    def window(self, start: float, stop: float) -> "MeasuredData":
        """The samples with start <= time <= stop, same bench and start values."""
        keep = (self.time >= start) & (self.time <= stop)
        cut = lambda columns: {name: values[keep] for name, values in columns.items()}  # noqa: E731
        return replace(self, time=self.time[keep], signals=cut(self.signals), std=cut(self.std),
                       inputs=cut(self.inputs), source=f"{self.source} [{start:g}, {stop:g}] s")


# Errors are compared as mean squares: larger values overflow float64 when squared and summed.
MAX_MAGNITUDE = 1e150


def load_data(path: str | os.PathLike, info, *, min_samples: int = 2) -> MeasuredData:
    """Read a data CSV and its sidecar, checked against the FMU's variables (`info`: ModelInfo)."""
    from .simulation.inputs import read_csv_signals
    path = Path(path)
    time, columns = read_csv_signals(path)
    check_plain_numbers(path)
    if time.size < min_samples:
        raise FmuBuilderError(f"{path} has {time.size} time stamp(s); give at least {min_samples}")
    names, uncertainty = split_uncertainty_columns(["time", *columns])
    signals, inputs = {}, {}
    for name in names:
        var = info.variable(name)     # an unknown name fails here with the close names
        if var.type != "Real":
            raise FmuBuilderError(f"{path}: column '{name}' is a {var.type} variable of the model; "
                                  "measured signals must be Real variables")
        if not np.all(np.isfinite(columns[name])):
            raise FmuBuilderError(f"{path}: column '{name}' holds non-finite values; remove or fill them")
        largest = float(np.max(np.abs(columns[name]))) if columns[name].size else 0.0
        if largest > MAX_MAGNITUDE:
            raise FmuBuilderError(f"{path}: column '{name}' holds values up to {largest:.3g}, beyond {MAX_MAGNITUDE:g}, "
                                  "whose squared errors overflow; check the column's values and units")
        if var.causality == "input":
            inputs[name] = columns[name]
        elif var.is_parameter:
            raise FmuBuilderError(f"{path}: column '{name}' is a parameter; give parameters as start values "
                                  f"({name}=VALUE) or in the sidecar {sidecar_path(path).name}")
        else:
            signals[name] = columns[name]
    if not signals:
        raise FmuBuilderError(f"{path} has no measured signal: add columns named after FMU states or outputs, "
                              "e.g. time,speed")
    std = {name: np.abs(columns[column]) for name, column in uncertainty.items() if name in signals}
    sidecar = read_sidecar(path) or {}
    _check_start_types(sidecar.get("start_values") or {}, info, sidecar_path(path))
    bench = sidecar.get("bench") or {}
    return MeasuredData(time, signals, std, inputs, source=str(path), sensor_lag=sensor_lag_of(sidecar, path),
                        runs=max(1, int(bench.get("runs", DEFAULT_RUNS))),
                        fine_step=_positive_or_none(bench.get("fine_step")),
                        start_values=dict(sidecar.get("start_values") or {}), path=path)


def sensor_lag_of(sidecar: dict, path: str | os.PathLike = "data") -> float:
    """The sensor lag a sidecar declares: `sensor_lag`, else the bench's `lag`, else 0."""
    value = sidecar.get("sensor_lag", (sidecar.get("bench") or {}).get("lag", 0.0))
    try:
        lag = float(value or 0.0)
    except (TypeError, ValueError):
        lag = -1.0
    if not lag >= 0.0 or not np.isfinite(lag):
        raise FmuBuilderError(f"{sidecar_path(path)}: sensor lag {value!r} is not a time constant >= 0 s; fix it")
    return lag


def sidecar_path(csv_path: str | os.PathLike) -> Path:
    """The metadata JSON belonging to a data file: ``<csv path>.json``."""
    csv_path = Path(csv_path)
    return csv_path.with_name(csv_path.name + ".json")


def read_sidecar(csv_path: str | os.PathLike) -> dict | None:
    """The metadata of a data file, or None when it has no sidecar."""
    meta_path = sidecar_path(csv_path)
    if not meta_path.is_file():
        return None
    try:
        meta = json.loads(meta_path.read_text())
    except ValueError as exc:
        raise FmuBuilderError(f"{meta_path} is not valid JSON ({exc}); fix it or regenerate it with "
                              "`fmubuilder synth`") from None
    if not isinstance(meta, dict):
        raise FmuBuilderError(f"{meta_path} holds no JSON object; write {{\"start_values\": {{...}}}} or delete it")
    _check_sidecar(meta, meta_path)
    return meta


def _check_sidecar(meta: dict, where: Path) -> None:
    """The fields fmubuilder reads, each of its type: one line naming the field, never an internal error."""
    def fail(field: str, value, wanted: str):
        raise FmuBuilderError(f"{where}: {field} is {json.dumps(value)[:60]}, not {wanted}; fix it or delete the field")

    def number(field: str, value, least: float | None = None, whole: bool = False, above: bool = False):
        if value is None:
            return
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            fail(field, value, "a finite number")
        if whole and value != int(value):
            fail(field, value, "a whole number")
        if least is not None and (value <= least if above else value < least):
            fail(field, value, f"a number {'>' if above else '>='} {least:g}")

    def mapping(field: str, value) -> dict:
        if value is not None and not isinstance(value, dict):
            fail(field, value, "a JSON object")
        return value or {}

    starts = mapping("start_values", meta.get("start_values"))
    for name, value in starts.items():
        field = f"start_values.{name}"
        if isinstance(value, str):
            if "_" in value and _reads_as_number(value):
                fail(field, value, "a number (write it without '_')")
        elif isinstance(value, bool):
            pass
        elif isinstance(value, (int, float)):
            number(field, value)
        else:
            fail(field, value, "a number, true/false or a string")
    number("sensor_lag", meta.get("sensor_lag"))     # its range: sensor_lag_of
    bench = mapping("bench", meta.get("bench"))
    number("bench.lag", bench.get("lag"))
    number("bench.runs", bench.get("runs"), 1, whole=True)
    number("bench.fine_step", bench.get("fine_step"), 0.0, above=True)
    mapping("truth_model", meta.get("truth_model"))
    mapping("truth.parameters", mapping("truth", meta.get("truth")).get("parameters"))


def _check_start_types(starts: dict, info, where: Path) -> None:
    """Each start value of the sidecar names a model variable and fits its type (a number for a Real or
    Integer, true/false for a Boolean, text for a String): one line, not a failure inside the FMU."""
    for name, value in starts.items():
        var = info.variables.get(name)
        if var is None:
            continue    # a name the model lacks is the stage's to report, as for --start
        numeric = isinstance(value, (int, float)) and not isinstance(value, bool)
        if var.type in ("Real", "Integer", "Enumeration"):
            fits = numeric or (isinstance(value, str) and _reads_as_number(value))
            if fits and var.type != "Real" and float(value) != int(float(value)):
                fits = False
        elif var.type == "Boolean":
            fits = isinstance(value, bool) or value in (0, 1) or (isinstance(value, str) and value.strip().lower()
                                                                   in ("true", "false", "0", "1"))
        else:
            fits = isinstance(value, str)
        if not fits:
            raise FmuBuilderError(f"{where}: start_values.{name} is {json.dumps(value)[:60]}, not a value of the "
                                  f"{var.type} variable {name}; fix it or delete it")


def _reads_as_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def check_plain_numbers(path: str | os.PathLike) -> None:
    """A data CSV's cells are numbers as written: Python (and numpy) read '1_000' as 1000, a typo far
    more often than a thousand; refused with its row and column."""
    import csv
    with open(path, newline="", encoding="utf-8-sig", errors="replace") as file:
        reader = csv.reader(file)
        header = next(reader, [])
        for number, row in enumerate(reader, start=2):
            if not any("_" in cell for cell in row):
                continue
            for column, cell in zip(header, row):
                if "_" in cell:
                    raise FmuBuilderError(f"{path}, row {number}, column '{column.strip()}': '{cell.strip()}' is not "
                                          "a plain number; write it without '_' (e.g. 1000, not 1_000)")


def split_uncertainty_columns(names: Sequence[str]) -> tuple[list[str], dict[str, str]]:
    """Split data columns into signals and spread columns: ``X_std`` is the spread of ``X``
    when ``X`` is a column too. Returns (signals, {signal: its _std column})."""
    present = set(names)
    uncertainty = {n[: -len(UNCERTAINTY_SUFFIX)]: n for n in names
                   if n.endswith(UNCERTAINTY_SUFFIX) and n[: -len(UNCERTAINTY_SUFFIX)] in present}
    signals = [n for n in names if n != "time" and n not in uncertainty.values()]
    return signals, uncertainty


def first_order_lag(time: np.ndarray, signal: np.ndarray, tau: float) -> np.ndarray:
    """The sensor model: output of ``tau * dy/dt = u - y`` with ``y(t0) = u(t0)`` for an input
    ``u`` linear between the given points. Repeated time points (before/after an event) are a
    step of the input and leave the output unchanged."""
    signal = np.asarray(signal, dtype=float)
    if tau <= 0.0 or signal.size < 2:
        return signal.copy()
    h = np.diff(np.asarray(time, dtype=float))
    moves = h > 1e-12 * tau                          # the others are an event's two sides
    moving = np.flatnonzero(moves)
    hm, u0, u1 = h[moving], signal[moving], signal[moving + 1]
    decay = np.exp(-hm / tau)
    # the exact response over a step to an input linear in it: the start value's share (1 - decay)
    # and the change's, 1 - tau/h * (1 - decay)
    share = -np.expm1(-hm / tau)
    forcing = share * u0 + (1.0 - tau / hm * share) * (u1 - u0)
    after = np.concatenate(([signal[0]], linear_recurrence(decay, forcing, signal[0])))
    steps_before = np.concatenate(([0], np.cumsum(moves)))
    return after[steps_before]


# |log| of the products of decay ratios within one lfilter call: exp(200) is far from overflow
_RATIO_SPAN = 200.0


def linear_recurrence(a: np.ndarray, x: np.ndarray, y0: float) -> np.ndarray:
    """y_j = a_j y_(j-1) + x_j for j = 0..n-1 from y_(-1) = y0, with a_j > 0, in compiled loops.
    With a_j = a0 r_j and R_j = r_0 ... r_j, z_j = y_j / R_j follows z_j = a0 z_(j-1) + x_j / R_j,
    a constant-coefficient filter (scipy's lfilter); R is restarted before it leaves exp(+-200)
    (grids with cut steps), so every value stays far inside the float range."""
    from scipy.signal import lfilter
    a, x = np.asarray(a, dtype=float), np.asarray(x, dtype=float)
    out = np.empty_like(x)
    if a.size == 0:
        return out
    a0 = float(np.median(a))
    log_ratio = np.log(a / a0)
    start, y = 0, float(y0)
    while start < a.size:
        span = np.cumsum(log_ratio[start:])
        beyond = np.flatnonzero(np.abs(span) > _RATIO_SPAN)
        stop = start + (max(int(beyond[0]), 1) if beyond.size else span.size)
        products = np.exp(span[:stop - start])
        z, _ = lfilter([1.0], [1.0, -a0], x[start:stop] / products, zi=[a0 * y])
        out[start:stop] = z * products
        start, y = stop, float(out[stop - 1])
    return out


def sensor_reading(time: np.ndarray, values: np.ndarray, at: np.ndarray, tau: float) -> np.ndarray:
    """What a sensor with a first-order lag `tau` shows at the times `at` of a run recorded at `time`
    (both sides of an event recorded): the lagged values, linear between records, the settled one
    at an event's time (simulation.results.sample_settled)."""
    from .simulation.results import sample_settled
    return sample_settled(time, first_order_lag(time, np.asarray(values, dtype=float), tau), at)


def _intercept(t: np.ndarray, y: np.ndarray, noise_variance: float | None = None) -> tuple[float, float]:
    """Value at t = 0 of the least-squares line through (t, y) and its standard error, widened for
    residuals correlated from sample to sample (a filtered sensor's noise): by sqrt((1 + r) / (1 - r))
    with r their lag-one autocorrelation. The noise variance the data give (their spread columns) is
    the floor of the residuals' own: a handful of residuals with a line's two degrees of freedom
    taken out can be small by chance, and a start rejected on them is a noisy sample's value (on the
    DC drive's speed-current loss training data the energy's first five samples put the line at
    -1.37 J with a standard error of 0.18 J from the residuals, 0.53 J from the noise: the model's
    true 0 J was rejected, and the trained ANN learned to make up the 1.37 J)."""
    design = np.column_stack([np.ones_like(t), t])
    coefficients, *_ = np.linalg.lstsq(design, y, rcond=None)
    residual = y - design @ coefficients
    variance = max(float(residual @ residual) / max(t.size - 2, 1), noise_variance or 0.0)
    r = float(residual[1:] @ residual[:-1]) / float(residual @ residual) if np.any(residual) else 0.0
    r = min(max(r, 0.0), 0.9)
    unit = float(np.linalg.pinv(design.T @ design)[0, 0])
    return float(coefficients[0]), math.sqrt(variance * unit * (1.0 + r) / (1.0 - r))


def _positive_or_none(value) -> float | None:
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number if number > 0 else None
