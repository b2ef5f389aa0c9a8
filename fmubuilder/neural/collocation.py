"""Samples for collocation pre-training (CCPT): the FMU along the measured trajectory.

The FMU is simulated with its measured states forced to the data after every step, so its sampled
controllers and relays react to the measured behaviour; along that run the ANN inputs and the
FMU's channel derivatives are recorded, and the derivative of each measured state is estimated
from the data by a local linear fit over a window (robust to sensor noise, any time stamps).

The states forced are the local fits' values, not the raw samples: a controller fed the raw noise
turns it into actuator noise, which relays and saturations bend into a bias. And they are read
`sensor_lag` later than the time simulated: a first-order sensor delays a smooth signal by its time
constant, and a controller forced with the delayed speed pushes harder than the real one did
(on the VLDM's driver that bias is of the size of the effect itself).
"""
from __future__ import annotations

import numpy as np
import torch

from ..data import MeasuredData
from ..simulation.results import equal_along
from .core_gradient import simulate_without_gradient
from .model import NeuralFMU
from .solve import ElementStart, simulate

MAX_SAMPLES = 50_000
# A window whose local line leaves more than this many times the typical residual spans a step or a
# kink (see smooth_windows).
ROUGHNESS_LIMIT = 2.0


def collocation_samples(model: NeuralFMU, data: MeasuredData, step: float, solver: str, window: float, inputs,
                        sensor_lag: float = 0.0, force: bool = True):
    """(ANN inputs [N, n_in], FMU channel derivatives [N, C], measured derivatives [N, C], mask [N, C])
    or None when no channel's state is measured. sensor_lag: the sensors' first-order time constant.
    force=False: along the plain run instead (see forced_channel_run)."""
    run = forced_channel_run(model, data, step, solver, window, inputs, sensor_lag, force)
    return None if run is None else samples_along(run, model, data, window, sensor_lag)[1:]


def samples_along(run, model: NeuralFMU, data: MeasuredData, window: float, sensor_lag: float = 0.0):
    """collocation_samples from a forced_channel_run, with the absolute times of the points kept:
    (times [N], ANN inputs, FMU channel derivatives, measured derivatives, mask)."""
    times, ann_inputs, fmu_channels, channel_states, aliases = run
    every = max(1, len(times) // MAX_SAMPLES)
    keep = slice(0, len(times), every)
    times, ann_inputs, fmu_channels = times[keep], ann_inputs[keep], fmu_channels[keep]
    measured = np.zeros_like(fmu_channels)
    mask = np.zeros(fmu_channels.shape, dtype=bool)
    forced = [s for s in model.state_names() if s in data.signals]
    smooth = smooth_windows(data, forced, times + sensor_lag, window)
    for j, state in enumerate(channel_states):
        if aliases[j] is not None:
            # the derivative is measured itself: its local line's value, no slope (on the DC drive's
            # loss data the energy's slope left 2.5 W rms of noise against a loss of rms 4.9 W)
            value, _, valid = local_fit(data.time, data.signals[aliases[j]], times + sensor_lag, window)
            measured[:, j], mask[:, j] = value, valid & smooth
        elif state in data.signals:
            _, slope, valid = local_fit(data.time, data.signals[state], times + sensor_lag, window)
            measured[:, j], mask[:, j] = slope, valid & smooth
    return times, ann_inputs, fmu_channels, measured, mask


def integral_samples(model: NeuralFMU, data: MeasuredData, step: float, solver: str, inputs,
                     sensor_lag: float = 0.0, span: float = 0.5, force: bool = True):
    """The weak-form counterpart of collocation_samples: over windows [a, b] of `span` seconds,
    x(b) - x(a) = integral of (FMU derivative + missing term) dt, with no window left out (the state
    is continuous where its derivative jumps, at a friction's sign change or a load step).
    Returns (ANN inputs on the forced run's whole grid [N, n_in], FMU channel derivatives on it
    [N, C], WindowMeans of the windows, measured mean derivative (x(b) - x(a)) / (b - a) [W, C],
    mask [W, C]) or None when no channel's state is measured. The window edges are the sample times
    one sensor lag earlier (a lagging sensor shows the state then); x there is the sample itself
    (the local lines' values there were worse: docs/MEASUREMENTS.md). Consecutive windows overlap:
    one starts at every sample. The states are forced to the samples interpolated,
    not to local lines: a line through a load step smears the current over the line's span, and
    the integral of the FMU's derivative over a window near the step with it (on the DC drive's
    Coulomb data the target's rms error over 0.5 s windows was 2.34 with 0.5 s lines, 0.74 with
    the samples, against a friction of rms 4.8 rad/s^2). force=False: along the plain run instead."""
    run = forced_channel_run(model, data, step, solver, 0.0, inputs, sensor_lag, force)
    if run is None:
        return None
    times, ann_inputs, fmu_channels, channel_states, _ = run
    lo, hi = window_edges(data.time - sensor_lag, times[0], times[-1], span)
    means = WindowMeans(times, (data.time - sensor_lag)[lo], (data.time - sensor_lag)[hi])
    measured = np.zeros((len(lo), len(channel_states)))
    mask = np.zeros(measured.shape, dtype=bool)
    for j, state in enumerate(channel_states):
        if state in data.signals:
            values = data.signals[state]
            measured[:, j] = (values[hi] - values[lo]) / (data.time[hi] - data.time[lo])
            mask[:, j] = True
    return ann_inputs, fmu_channels, means, measured, mask


def window_edges(edge_times: np.ndarray, first: float, last: float, span: float):
    """Index pairs (lo, hi) of the edges within [first, last]: a window from every edge to the first
    edge at least `span` later (at least the next one)."""
    inside = np.flatnonzero((edge_times >= first) & (edge_times <= last))
    if len(inside) < 2:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    t = edge_times[inside]
    hi = np.maximum(np.searchsorted(t, t + span - 1e-9, side="left"), np.arange(1, len(t) + 1))
    complete = hi < len(t)
    return inside[complete], inside[hi[complete]]


class WindowMeans:
    """The mean over each window [a, b] of a signal given on a time grid, as a linear map in torch:
    the trapezoid rule's running integral on the grid, interpolated linearly at a and b. Applied
    to the ANN's output along the forced run, it is what the measured increments are compared with."""

    def __init__(self, grid: np.ndarray, starts: np.ndarray, ends: np.ndarray):
        self.grid = np.asarray(grid, dtype=float)
        self.count = len(starts)
        self._dt = torch.from_numpy(np.diff(self.grid))[:, None]
        self._a = self._position(starts)
        self._b = self._position(ends)
        self._length = torch.from_numpy(np.asarray(ends, dtype=float) - np.asarray(starts, dtype=float))[:, None]

    def _position(self, at: np.ndarray):
        index = np.clip(np.searchsorted(self.grid, at, side="right") - 1, 0, len(self.grid) - 2)
        weight = (at - self.grid[index]) / (self.grid[index + 1] - self.grid[index])
        return torch.from_numpy(index), torch.from_numpy(np.clip(weight, 0.0, 1.0))[:, None]

    def __call__(self, values: torch.Tensor) -> torch.Tensor:
        """values [N, C] on the grid -> means [W, C] over the windows."""
        steps = 0.5 * (values[1:] + values[:-1]) * self._dt.to(values.dtype)
        running = torch.cat([torch.zeros_like(values[:1]), torch.cumsum(steps, dim=0)])

        def at(position):
            index, weight = position
            weight = weight.to(values.dtype)
            return running[index] * (1.0 - weight) + running[index + 1] * weight
        return (at(self._b) - at(self._a)) / self._length.to(values.dtype)

    def subset(self, rows):
        """The windows selected by the boolean or index array `rows`."""
        chosen = WindowMeans.__new__(WindowMeans)
        chosen.grid, chosen._dt = self.grid, self._dt
        rows = torch.as_tensor(rows)
        chosen._a = (self._a[0][rows], self._a[1][rows])
        chosen._b = (self._b[0][rows], self._b[1][rows])
        chosen._length = self._length[rows]
        chosen.count = len(chosen._length)
        return chosen


def _interpolated(time, values):
    return lambda at: (np.interp(at, time, values),)


def forced_channel_run(model: NeuralFMU, data: MeasuredData, step: float, solver: str, window: float, inputs,
                       sensor_lag: float = 0.0, force: bool = True):
    """The forced run (forced_run: the measured states set to their local lines through +-window/2,
    or with window 0 to the samples interpolated linearly, read a sensor lag later) on its whole
    grid: (absolute times [N], ANN inputs [N, n_in], FMU channel derivatives [N, C], the channels'
    state names, for each channel the measured output equal to its derivative or None), or None
    when no channel's state is measured. force=False: the plain run, nothing forced, the same
    record (where a controller reacts to the forced noise more than to the effect, the model's own
    run is the better reference; see warm_start.ESTIMATES)."""
    config = model.config
    state_names = model.state_names()
    derivative_names = [v.name for v in model.info.derivatives]
    channel_states = [state_names[derivative_names.index(c)] for c in config.channels]
    if not any(s in data.signals for s in channel_states):
        return None
    forced = [s for s in state_names if s in data.signals] if force else []
    if window > 0:
        fits = [local_fitter(data.time, data.signals[s], window) for s in forced]
    else:
        fits = [_interpolated(data.time, data.signals[s]) for s in forced]

    def values(t):
        t = np.atleast_1d(np.asarray(t, dtype=float)) + sensor_lag
        return np.stack([fit(t)[0] for fit in fits], axis=1)

    outputs = [v.name for v in model.info.outputs if v.name in data.signals and v.name not in state_names]
    names = list(dict.fromkeys(config.inputs + config.channels + outputs))
    run = forced_run(model, data, step, solver, forced, values, names, inputs)
    ann_inputs = np.stack([run.numpy(n)[:, 0] for n in config.inputs], axis=1)
    fmu_channels = np.stack([run.numpy(c)[:, 0] for c in config.channels], axis=1)
    measured_outputs = {n: run.numpy(n)[:, 0] for n in outputs}
    # a measured output the model sets equal to the channel's derivative (a power to der(energy))
    aliases = [next(iter(equal_along(measured_outputs, fmu_channels[:, j])), None) for j in range(len(config.channels))]
    return data.start + run.times, ann_inputs, fmu_channels, channel_states, aliases


def smooth_windows(data: MeasuredData, states: list[str], at: np.ndarray, window: float) -> np.ndarray:
    """Whether every forced state is a straight line plus noise within +-window/2 of each time in
    `at`: the residual of its local linear fit at most ROUGHNESS_LIMIT times that state's median
    residual (most windows hold only noise). A window across a load step or a kink of a set-point
    bends: there the line's slope and value, hence the estimate of the missing term, are wrong by
    far more than the effect (on the DC drive, near the load steps, by several times its size)."""
    smooth = np.ones(at.shape, dtype=bool)
    for state in states:
        roughness = local_roughness(data.time, data.signals[state], at, window)
        typical = np.nanmedian(roughness)
        if np.isfinite(typical) and typical > 0:
            smooth &= np.nan_to_num(roughness, nan=np.inf) <= ROUGHNESS_LIMIT * typical
    return smooth


def local_roughness(time: np.ndarray, values: np.ndarray, at: np.ndarray, window: float) -> np.ndarray:
    """Root mean square residual of the least-squares line through the samples within +-window/2 of
    each time in `at` (nan where fewer than 3 samples lie in the window)."""
    origin, scale = time[0], max(float(np.std(values)), 1e-300)
    t, y = time - origin, (values - np.mean(values)) / scale     # centred: the sums below cancel less
    prefix = [np.concatenate(([0.0], np.cumsum(q))) for q in (np.ones_like(t), t, y, t * t, t * y, y * y)]
    lo = np.searchsorted(time, at - 0.5 * window, side="left")
    hi = np.searchsorted(time, at + 0.5 * window, side="right")
    s0, st, sy, stt, sty, syy = (p[hi] - p[lo] for p in prefix)
    count = np.maximum(s0, 1)
    tt, ty, yy = stt - st * st / count, sty - st * sy / count, syy - sy * sy / count
    residual = np.maximum(yy - np.where(tt > 0, ty * ty / np.where(tt > 0, tt, 1.0), 0.0), 0.0)
    return np.where(s0 >= 3, np.sqrt(residual / np.maximum(s0 - 2, 1)) * scale, np.nan)


def forced_run(model: NeuralFMU, data: MeasuredData, step: float, solver: str, forced: list[str], values,
               record: list[str], inputs):
    """The FMU alone (ANN off, no gradient) over the data's span, with the states `forced` set to
    values(t) [len(t), len(forced)] after every step and the other states to the plain run's
    (see with_plain_unmeasured); none forced: the plain run."""
    if forced:
        forced, values = with_plain_unmeasured(model, data, step, solver, forced, values, inputs)
    return _run(model, data, step, solver, forced, values, record, inputs)


def with_plain_unmeasured(model: NeuralFMU, data: MeasuredData, step: float, solver: str, forced: list[str],
                          values, inputs):
    """(forced states, values(t)) extended by the integrators the data do not measure, at the plain
    run's values. Left free along the measured run, a state whose derivative does not read the state
    itself (a controller's integrator) integrates the measured states' noise: a random walk. On the
    DC drive's loss data the speed controller's integrator drifted by 0.58 rms (its range 5.6),
    which put the model's der(energy) off by 16 W on average against a loss of rms 4.9 W. The plain
    run's is the truth's where the effect does not feed back into it, and close where it does
    (0.03-0.09 rms on the DC drive's frictions). A state that reads itself (a current through an
    inductance) forgets its past and follows the forced states as the truth's did: it stays free,
    as do the states of a model that declares no dependencies."""
    others = unmeasured_integrators(model.info, forced)
    if not others:
        return forced, values
    plain = _run(model, data, step, solver, [], None, others, inputs)
    grid = data.start + np.asarray(plain.times, dtype=float)
    columns = [np.asarray(plain.numpy(s)[:, 0], dtype=float) for s in others]

    def extended(t):
        t = np.atleast_1d(np.asarray(t, dtype=float))
        measured = np.asarray(values(t), dtype=float).reshape(len(t), len(forced))
        return np.concatenate([measured, np.stack([np.interp(t, grid, c) for c in columns], axis=1)], axis=1)
    return [*forced, *others], extended


def unmeasured_integrators(info, measured) -> list[str]:
    """The model's states not in `measured` whose derivative, by the declared dependencies, does
    not read the state itself (a controller's integrator): those that follow the plain run."""
    return [v.name for v in info.states if v.name not in measured and is_integrator(info, v.name)]


def is_integrator(info, state: str) -> bool:
    """Whether the state's derivative, by the declared dependencies, does not read the state."""
    derivative = info.derivatives[[v.name for v in info.states].index(state)].name
    dependencies = info.dependencies.get(derivative)
    return dependencies is not None and state not in dependencies


def _run(model: NeuralFMU, data: MeasuredData, step: float, solver: str, forced: list[str], values,
         record: list[str], inputs):
    state_names = model.state_names()
    start = values(np.array([data.start]))[0] if forced else None
    first = ElementStart(data.start, states=dict(zip(forced, start)) if forced else None)
    forcing = ([state_names.index(s) for s in forced], values) if forced else None
    with torch.no_grad(), model.topology.ann_off():
        if forcing is None:     # the plain run: in the compiled core where it runs the model
            return simulate_without_gradient(model, data.stop - data.start, step, starts=[first], record=record,
                                             solver=solver, inputs=inputs)
        return simulate(model, data.stop - data.start, step, starts=[first], record=record, solver=solver,
                        inputs=inputs, forcing=forcing)


def local_slope(time: np.ndarray, values: np.ndarray, at: np.ndarray, window: float):
    """Slope of a least-squares line through the samples within +-window/2 of each time in `at`;
    (slopes, valid) where valid needs at least 3 samples."""
    _, slope, valid = local_fit(time, values, at, window)
    return slope, valid


def local_fit(time: np.ndarray, values: np.ndarray, at: np.ndarray, window: float):
    """Value and slope at each time in `at` of a least-squares line through the samples within
    +-window/2 of it; (values, slopes, valid). Where fewer than 3 samples lie in the window
    (valid false) the slope is 0 and the value the data's, interpolated."""
    return local_fitter(time, values, window)(at)


def local_fitter(time: np.ndarray, values: np.ndarray, window: float):
    """local_fit for one signal and window, its running sums computed once: at -> (values, slopes, valid)."""
    origin = time[0]
    t = time - origin
    prefix = [np.concatenate(([0.0], np.cumsum(q))) for q in (np.ones_like(t), t, values, t * t, t * values)]

    def fit(at):
        lo = np.searchsorted(time, at - 0.5 * window, side="left")
        hi = np.searchsorted(time, at + 0.5 * window, side="right")
        s0, st, sy, stt, sty = (p[hi] - p[lo] for p in prefix)
        denominator = s0 * stt - st * st
        valid = (s0 >= 3) & (denominator > 1e-12 * np.maximum(s0 * stt, 1e-300))
        slope = np.where(valid, (s0 * sty - st * sy) / np.where(valid, denominator, 1.0), 0.0)
        count = np.maximum(s0, 1)
        value = np.where(valid, sy / count + slope * (at - origin - st / count), np.interp(at, time, values))
        return value, slope, valid
    return fit
