"""Synthetic measurements: what a test bench would log if the truth were a given FMU.

:func:`measure` simulates a "truth" FMU (for example a VLDM variant with an effect the
declared model lacks) and turns the noise-free trajectories into measured data the way a
chassis dynamometer and its data logger do; :func:`write_measurement` stores the result.

The bench model, in the order it is applied:

1. **Fine simulation.** fmubuilder's engine (dopri5, rtol 1e-8) simulates the truth FMU on a
   grid of ``fine_step`` (0.01 s, the VLDM controller rate) and also records the values just
   before and after every event, so steps of the signals (relay switches, controller
   ticks) stay steps instead of becoming ramps between grid points.
2. **Sensor lag.** Each logged signal passes a first-order low-pass filter with time constant
   ``lag`` (0.1 s): ``lag * dy/dt = u - y``, starting settled (``y = u`` at the start).
   It is integrated exactly for a signal that is linear between the recorded points.
3. **Time stamps.** The logger samples at ``sample_rate`` (10 Hz); every stamp after the
   first is jittered uniformly by up to ``jitter`` periods (0.25) and rounded to the clock
   resolution ``time_resolution`` (1 ms). The first stamp is the start time, so the first
   row holds the initial state. Stamps are strictly increasing and not equidistant.
4. **Sensor noise.** Gaussian noise with a per-signal standard deviation (``noise_std``) is
   added to every sample of every run, independent between signals and runs. Its colour
   (``noise_model``) is one of :data:`NOISE_MODELS`, all with the same standard deviation:

   * ``white``: independent from sample to sample;
   * ``ar1``: correlated between successive samples, ``e[k] = rho e[k-1] + sqrt(1 - rho^2) w[k]``
     (``noise_rho``), as a logger's digital smoothing leaves it;
   * ``lowpass``: white noise through an analogue low-pass of ``noise_filter_order`` first-order
     stages with time constant ``noise_filter_tau`` [s], sampled at the stamps: the noise
     of a filtered sensor (one stage of 0.1 s at 10 Hz gives rho = exp(-1) = 0.37).

   Defaults: :data:`DEFAULT_NOISE_STD`. The energy is the analyser's own integral of its
   high-rate power reading, so it carries a small resolution noise of its own, not an
   integral of the logged (noisy, 10 Hz) power.
5. **Repeated runs.** The cycle is driven ``runs`` times (2). The runs share the logger's
   time stamps and differ in their noise realisations. Optionally (``run_variation``,
   off by default) each run also scales some real parameters of the truth FMU by
   ``1 + N(0, rel_std)``, e.g. ``rolling_coefficient`` for tyre temperature differences
   between runs; each run is then simulated on its own.

Only the requested signals are logged (default speed, power, energy); controller states and
other internals of the truth FMU never appear in the data.

The data file is the format data.py reads: ``time``, one column per signal (the mean over the
runs), one ``<signal>_std`` per signal (the sample standard deviation over the runs, ddof=1: an
estimate of one run's sensor noise), and a sidecar ``<csv>.json`` with the truth model, the start
values (pass them again as ``--start cycle=1`` to simulate or train on the data), the bench settings
and the seed. Parameters that make the truth differ from its FMU are recorded only under ``truth``,
a key the diagnosis never reads: real data come without it. Everything is deterministic given the seed.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from .data import UNCERTAINTY_SUFFIX, first_order_lag, sidecar_path
from .errors import FmuBuilderError, suggestion
from .files import file_sha256, refuse_existing, write_atomically

DEFAULT_SIGNALS = ("speed", "power", "energy")

# Standard deviations of the sensor noise of one run, in the signal's unit.
DEFAULT_NOISE_STD = {
    "speed": 0.02,         # m/s: roller encoder of the dynamometer
    "power": 100.0,        # W: power analyser on the HV battery
    "energy": 100.0,       # J: resolution of the analyser's energy integral
    "acceleration": 0.05,  # m/s2: differentiated roller speed
    "position": 0.1,       # m: integrated roller speed
}

# Relative tolerance of the truth simulation: far below the sensor noise.
TRUTH_RTOL = 1e-8

NOISE_MODELS = ("white", "ar1", "lowpass")
FORMAT = "fmubuilder-measurement/1"


@dataclass(frozen=True)
class BenchSettings:
    """How the test bench logs the truth FMU (see the module docstring for the model)."""

    signals: tuple[str, ...] = DEFAULT_SIGNALS
    noise_std: Mapping[str, float] = field(default_factory=dict)  # overrides DEFAULT_NOISE_STD
    sample_rate: float = 10.0        # Hz, nominal logger rate
    jitter: float = 0.25             # max deviation of a stamp from its nominal time, in periods
    time_resolution: float = 1e-3    # s, logger clock resolution
    lag: float = 0.1                 # s, time constant of the first-order sensor filter
    runs: int = 2
    run_variation: Mapping[str, float] = field(default_factory=dict)  # parameter -> relative std per run
    fine_step: float = 0.01          # s, grid of the truth simulation
    seed: int = 0
    noise_model: str = "white"       # one of NOISE_MODELS
    noise_rho: float = 0.0           # ar1: correlation of successive samples
    noise_filter_tau: float = 0.0    # lowpass: time constant of each stage [s]
    noise_filter_order: int = 1      # lowpass: number of first-order stages

    def noise_of(self, signal: str) -> float:
        if signal in self.noise_std:
            return float(self.noise_std[signal])
        if signal in DEFAULT_NOISE_STD:
            return DEFAULT_NOISE_STD[signal]
        raise FmuBuilderError(
            f"no default sensor noise for signal '{signal}': give one with --noise {signal}=STD (0 for none)")

    def as_dict(self) -> dict:
        data = asdict(self)
        data["signals"] = list(self.signals)
        data["noise_std"] = {name: self.noise_of(name) for name in self.signals}
        data["run_variation"] = dict(self.run_variation)
        return data


@dataclass
class Measurement:
    """Logged data of all runs on common time stamps; ``true`` is the noise-free sensor
    output (lagged truth) of each run, kept for checking the generator."""

    time: np.ndarray                     # (n,)
    runs: dict[str, np.ndarray]          # signal -> (runs, n) noisy samples
    true: dict[str, np.ndarray]          # signal -> (runs, n) lagged, noise-free samples
    metadata: dict

    @property
    def signals(self) -> list[str]:
        return list(self.runs)

    def mean(self, signal: str) -> np.ndarray:
        return self.runs[signal].mean(axis=0)

    def std(self, signal: str) -> np.ndarray:
        samples = self.runs[signal]
        return samples.std(axis=0, ddof=1) if len(samples) > 1 else np.zeros(samples.shape[1])

    def columns(self) -> dict[str, np.ndarray]:
        """The CSV columns in file order."""
        columns = {"time": self.time}
        columns.update({name: self.mean(name) for name in self.signals})
        columns.update({name + UNCERTAINTY_SUFFIX: self.std(name) for name in self.signals})
        return columns


# ---------------------------------------------------------------------------------------
# Generation


def measure(fmu: str | os.PathLike, *, stop_time: float, start_time: float = 0.0,
            start_values: Mapping[str, object] | None = None,
            settings: BenchSettings = BenchSettings(),
            truth_parameters: Mapping[str, object] | None = None) -> Measurement:
    """Simulate the truth FMU and log it as the test bench described in the module docstring.

    truth_parameters: values that make the truth differ from the FMU's declared ones (e.g. a
    heavier car); unlike start_values they are not data a user would pass back to the model,
    so the sidecar records them only under ``truth``."""
    from .fmi import read_model_info

    fmu = Path(fmu)
    info = read_model_info(fmu)
    start_time, stop_time = float(start_time), float(stop_time)
    _check_settings(settings, start_time, stop_time)
    _check_signals(info, settings)
    start_values = _typed_start_values(info, start_values or {})
    truth_parameters = _typed_start_values(info, truth_parameters or {})

    seeds = np.random.SeedSequence(settings.seed).spawn(3)
    stamp_rng, variation_rng, noise_rng = (np.random.default_rng(s) for s in seeds)
    stamps = sample_times(start_time, stop_time, settings.sample_rate, settings.jitter,
                          settings.time_resolution, stamp_rng)
    run_starts = _run_start_values(info, {**start_values, **truth_parameters}, settings, variation_rng)

    runs = {name: np.empty((settings.runs, len(stamps))) for name in settings.signals}
    true = {name: np.empty((settings.runs, len(stamps))) for name in settings.signals}
    trajectories = {}
    for run, values in enumerate(run_starts):
        key = json.dumps(values, sort_keys=True)
        if key not in trajectories:  # without run variation all runs share one simulation
            trajectories[key] = simulate_fine(fmu, start_time, stop_time, values,
                                              list(settings.signals), settings.fine_step)
        fine_time, fine = trajectories[key]
        for name in settings.signals:
            lagged = first_order_lag(fine_time, fine[name], settings.lag)
            true[name][run] = np.interp(stamps, fine_time, lagged)
            runs[name][run] = true[name][run] + settings.noise_of(name) * unit_noise(stamps, settings, noise_rng)

    metadata = _metadata(fmu, info, start_time, stop_time, start_values, run_starts, settings)
    if truth_parameters:
        metadata["truth"] = {"parameters": truth_parameters}
    return Measurement(time=stamps, runs=runs, true=true, metadata=metadata)


def sample_times(start: float, stop: float, rate: float, jitter: float, resolution: float,
                 rng: np.random.Generator) -> np.ndarray:
    """Logger time stamps: nominal ``start + k / rate``, the first exact, the others jittered
    by up to ``jitter`` periods and rounded to the clock resolution; all within [start, stop]."""
    period = 1.0 / rate
    count = int(math.floor((stop - start) * rate + 1e-9)) + 1
    nominal = start + period * np.arange(count)
    offsets = rng.uniform(-jitter, jitter, count) * period
    offsets[0] = 0.0
    stamps = np.round((nominal + offsets) / resolution) * resolution
    stamps[0] = start
    stamps = stamps[stamps <= stop]
    if len(stamps) < 2 or np.any(np.diff(stamps) <= 0):
        raise FmuBuilderError(
            f"time stamps at {rate:g} Hz with jitter {jitter:g} and resolution {resolution:g} s are not "
            "strictly increasing: lower the jitter or the clock resolution")
    return stamps


def unit_noise(stamps: np.ndarray, settings: BenchSettings, rng: np.random.Generator) -> np.ndarray:
    """Stationary Gaussian noise of unit standard deviation at the stamps, coloured as
    ``settings.noise_model`` says (see the module docstring)."""
    count = len(stamps)
    if settings.noise_model == "white":
        return rng.standard_normal(count)
    if settings.noise_model == "ar1":
        from scipy.signal import lfilter
        rho = settings.noise_rho
        innovations = rng.standard_normal(count) * math.sqrt(1.0 - rho ** 2)
        innovations[0] = rng.standard_normal()           # start in the stationary distribution
        return lfilter([1.0], [1.0, -rho], innovations)
    return _lowpass_noise(stamps, settings, rng)


def _lowpass_noise(stamps: np.ndarray, settings: BenchSettings, rng: np.random.Generator) -> np.ndarray:
    """White noise on the fine grid through the cascade of first-order filters, started ten
    time constants early (settled) and scaled by the cascade's exact stationary gain."""
    from scipy.signal import lfilter
    step, tau, order = settings.fine_step, settings.noise_filter_tau, settings.noise_filter_order
    decay = math.exp(-step / tau)
    numerator, denominator = [1.0], [1.0]
    for _ in range(order):
        numerator = np.convolve(numerator, [1.0 - decay])
        denominator = np.convolve(denominator, [1.0, -decay])
    settle = int(math.ceil(10.0 * order * tau / step))
    grid = stamps[0] + step * np.arange(-settle, int(math.ceil((stamps[-1] - stamps[0]) / step)) + 2)
    filtered = lfilter(numerator, denominator, rng.standard_normal(grid.size))
    impulse = lfilter(numerator, denominator, np.r_[1.0, np.zeros(settle + 1)])
    return np.interp(stamps, grid, filtered) / math.sqrt(float(np.sum(impulse ** 2)))


def simulate_fine(fmu: Path, start_time: float, stop_time: float, start_values: Mapping[str, object],
                  names: Sequence[str], step: float) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Trajectories of ``names`` on a ``step`` grid plus the values before and after each event."""
    from .simulation import simulate
    result = simulate(fmu, start_time=start_time, stop_time=stop_time, start_values=dict(start_values),
                      variables=list(names), solver="dopri5", rtol=TRUTH_RTOL, output_interval=step,
                      record_events=True)
    if result.terminated_early:
        raise FmuBuilderError(
            f"the truth model {fmu.name} stopped itself at t={result.stop_time:g} s: measure up to that "
            "time at most (--stop-time)")
    return result.time, {name: np.asarray(result[name], dtype=float) for name in names}


# ---------------------------------------------------------------------------------------
# Checks of the user's input


def _check_settings(settings: BenchSettings, start_time: float, stop_time: float) -> None:
    if not math.isfinite(start_time) or not math.isfinite(stop_time) or stop_time <= start_time:
        raise FmuBuilderError(
            f"stop time {stop_time:g} s is not after the start time {start_time:g} s: pass a larger --stop-time")
    period = 1.0 / settings.sample_rate if settings.sample_rate > 0 else math.inf
    if stop_time - start_time < period:
        raise FmuBuilderError(
            f"{stop_time - start_time:g} s gives fewer than two samples at {settings.sample_rate:g} Hz: "
            "pass a larger --stop-time or a higher --sample-rate")
    if not 0.0 <= settings.jitter < 0.5:
        raise FmuBuilderError(f"jitter {settings.jitter:g} must be in [0, 0.5) periods so that stamps keep their order")
    if settings.runs < 1:
        raise FmuBuilderError(f"--runs {settings.runs}: the bench needs at least one run (2 for an uncertainty)")
    if settings.lag < 0:
        raise FmuBuilderError(f"sensor lag {settings.lag:g} s is negative: give a time constant >= 0")
    if not 0 < settings.fine_step <= period / 2:
        raise FmuBuilderError(
            f"simulation step {settings.fine_step:g} s must be positive and at most half the sample period {period:g} s")
    if not 0 < settings.time_resolution <= period / 10:
        raise FmuBuilderError(
            f"clock resolution {settings.time_resolution:g} s must be positive and at most a tenth of the sample period")
    for name, std in settings.noise_std.items():
        if not (math.isfinite(std) and std >= 0):
            raise FmuBuilderError(f"noise of '{name}' is {std!r}: give a standard deviation >= 0")
        if name not in settings.signals:
            raise FmuBuilderError(
                f"--noise {name}=... names no logged signal: log it with --signals or drop the option")
    for name, rel in settings.run_variation.items():
        if not (math.isfinite(rel) and rel >= 0):
            raise FmuBuilderError(f"run variation of '{name}' is {rel!r}: give a relative standard deviation >= 0")
    if settings.noise_model not in NOISE_MODELS:
        raise FmuBuilderError(f"noise model '{settings.noise_model}' is unknown: choose one of {', '.join(NOISE_MODELS)}")
    if settings.noise_model == "ar1" and not -1.0 < settings.noise_rho < 1.0:
        raise FmuBuilderError(f"AR(1) noise correlation {settings.noise_rho:g} must lie strictly between -1 and 1")
    if settings.noise_model == "lowpass":
        if not (math.isfinite(settings.noise_filter_tau) and settings.noise_filter_tau > 0):
            raise FmuBuilderError(
                f"low-pass noise needs a filter time constant > 0 s, got {settings.noise_filter_tau:g}")
        if settings.noise_filter_order not in (1, 2, 3, 4):
            raise FmuBuilderError(f"low-pass noise filter order {settings.noise_filter_order}: choose 1 to 4 stages")


def _check_signals(info, settings: BenchSettings) -> None:
    signals = settings.signals
    if not signals:
        raise FmuBuilderError("no signals to log: give comma-separated FMU variables, e.g. --signals speed,power")
    if len(set(signals)) != len(signals):
        raise FmuBuilderError(f"signal list {','.join(signals)} repeats a name: give each signal once")
    for name in signals:
        if name == "time":
            raise FmuBuilderError("'time' is always written; leave it out of --signals")
        var = info.variable(name, "signal")
        if var.type != "Real":
            raise FmuBuilderError(f"signal '{name}' is a {var.type} variable: log Real variables only")
        if name + UNCERTAINTY_SUFFIX in signals:
            raise FmuBuilderError(
                f"signals '{name}' and '{name}{UNCERTAINTY_SUFFIX}' would clash with the uncertainty column of '{name}'")
        settings.noise_of(name)  # fails early for a signal without a noise level


def _typed_start_values(info, start_values: Mapping[str, object]) -> dict[str, object]:
    from .fmi import convert_value
    return {name: convert_value(info.variable(name, "start value"), value) for name, value in start_values.items()}


def _run_start_values(info, start_values: dict, settings: BenchSettings,
                      rng: np.random.Generator) -> list[dict[str, object]]:
    """Start values of each run: the given ones, with the varied parameters scaled per run."""
    runs = []
    for _ in range(settings.runs):
        values = dict(start_values)
        for name, rel_std in sorted(settings.run_variation.items()):
            var = info.variables.get(name)
            if var is None or var.type != "Real" or not var.is_parameter:
                raise FmuBuilderError(
                    f"run variation of '{name}': only Real parameters of the FMU can vary between runs"
                    f"{suggestion(name, [p.name for p in info.parameters if p.type == 'Real'])}")
            nominal = float(values.get(name, var.start if var.start is not None else 0.0))
            values[name] = nominal * (1.0 + rng.normal(0.0, rel_std))
        runs.append(values)
    return runs


# ---------------------------------------------------------------------------------------
# Writing and reading


def check_data_path(path: str | os.PathLike, force: bool = False) -> Path:
    """Refuse a data path whose CSV or sidecar exists (unless ``force``) or whose folder is missing."""
    path = Path(path)
    for target in (path, sidecar_path(path)):
        if target.is_dir():
            raise FmuBuilderError(f"{target} is a directory; give a file name for the data, e.g. -o data.csv")
        refuse_existing(target, force)
    if not path.parent.is_dir():
        raise FmuBuilderError(f"folder {path.parent} does not exist; create it or choose another output path")
    return path


def write_measurement(measurement: Measurement, path: str | os.PathLike, *, force: bool = False,
                      extra_metadata: Mapping[str, object] | None = None) -> Path:
    """Write the data CSV and its sidecar JSON atomically; refuse to overwrite without ``force``."""
    path = check_data_path(path, force)
    metadata = dict(measurement.metadata)
    metadata["data_file"] = path.name
    metadata.update(extra_metadata or {})
    write_atomically(path, format_csv(measurement.columns(), measurement.metadata["bench"]["time_resolution"]))
    write_atomically(sidecar_path(path), json.dumps(metadata, indent=2) + "\n")
    return path


def format_csv(columns: Mapping[str, np.ndarray], time_resolution: float) -> str:
    """CSV text: time with the clock's decimals, values with 10 significant digits."""
    decimals = max(0, int(math.ceil(-math.log10(time_resolution) - 1e-9)))
    formats = [f"%.{decimals}f"] + ["%.10g"] * (len(columns) - 1)
    table = np.column_stack(list(columns.values()))
    lines = [",".join(columns)]
    lines += [",".join(fmt % value for fmt, value in zip(formats, row)) for row in table.tolist()]
    return "\n".join(lines) + "\n"


def _metadata(fmu: Path, info, start_time: float, stop_time: float, start_values: dict,
              run_starts: list[dict], settings: BenchSettings) -> dict:
    from . import __version__
    start_options = " ".join(f"--start {name}={_literal(value)}" for name, value in start_values.items())
    return {
        "format": FORMAT,
        "generator": f"fmubuilder {__version__} synth",
        "truth_model": {"file": fmu.name, "model_name": info.model_name, "guid": info.guid,
                        "sha256": file_sha256(fmu)},
        "start_time": start_time,
        "stop_time": stop_time,
        "start_values": start_values,
        "start_options": start_options,
        "seed": settings.seed,
        "bench": settings.as_dict(),
        "run_start_values": run_starts if settings.run_variation else None,
        "columns": {"time": "s, strictly increasing, non-equidistant logger stamps",
                    "<signal>": "mean over the runs",
                    "<signal>_std": "sample standard deviation over the runs (ddof=1); "
                                    "uncertainty of the mean = <signal>_std / sqrt(runs)"},
    }


def _literal(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return repr(value) if isinstance(value, float) else str(value)

