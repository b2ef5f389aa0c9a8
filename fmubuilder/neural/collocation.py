"""Samples for collocation pre-training (CCPT): the FMU along the measured trajectory.

The FMU is simulated with its measured states forced to the data after every step, so its sampled
controllers and relays react to the measured behaviour; along that run the ANN inputs and the
FMU's channel derivatives are recorded, and the derivative of each measured state is estimated
from the data by a local linear fit over a window (robust to sensor noise, any time stamps).
"""
from __future__ import annotations

import numpy as np
import torch

from ..data import MeasuredData
from .model import NeuralFMU
from .solve import ElementStart, simulate

MAX_SAMPLES = 50_000


def collocation_samples(model: NeuralFMU, data: MeasuredData, step: float, solver: str, window: float, inputs):
    """(ANN inputs [N, n_in], FMU channel derivatives [N, C], measured derivatives [N, C], mask [N, C])
    or None when no channel's state is measured."""
    config = model.config
    state_names = model.state_names()
    derivative_names = [v.name for v in model.info.derivatives]
    channel_states = [state_names[derivative_names.index(c)] for c in config.channels]
    if not any(s in data.signals for s in channel_states):
        return None
    forced = [s for s in state_names if s in data.signals]
    indices = [state_names.index(s) for s in forced]

    def values(t):
        return np.stack([np.interp(t, data.time, data.signals[s]) for s in forced], axis=1)

    names = list(dict.fromkeys(config.inputs + config.channels))
    with torch.no_grad(), model.topology.ann_off():
        run = simulate(model, data.stop - data.start, step, starts=[ElementStart(data.start, states=dict(
            zip(forced, values(np.array([data.start]))[0])))], record=names, solver=solver, inputs=inputs,
            forcing=(indices, values))
    times = data.start + run.times
    every = max(1, len(times) // MAX_SAMPLES)
    keep = slice(0, len(times), every)
    ann_inputs = np.stack([run.numpy(n)[keep, 0] for n in config.inputs], axis=1)
    fmu_channels = np.stack([run.numpy(c)[keep, 0] for c in config.channels], axis=1)
    measured = np.zeros_like(fmu_channels)
    mask = np.zeros(fmu_channels.shape, dtype=bool)
    for j, state in enumerate(channel_states):
        if state in data.signals:
            slope, valid = local_slope(data.time, data.signals[state], times[keep], window)
            measured[:, j], mask[:, j] = slope, valid
    return ann_inputs, fmu_channels, measured, mask


def local_slope(time: np.ndarray, values: np.ndarray, at: np.ndarray, window: float):
    """Slope of a least-squares line through the samples within +-window/2 of each time in `at`;
    (slopes, valid) where valid needs at least 3 samples."""
    origin = time[0]
    t = time - origin
    prefix = [np.concatenate(([0.0], np.cumsum(q))) for q in (np.ones_like(t), t, values, t * t, t * values)]
    lo = np.searchsorted(time, at - 0.5 * window, side="left")
    hi = np.searchsorted(time, at + 0.5 * window, side="right")
    s0, st, sy, stt, sty = (p[hi] - p[lo] for p in prefix)
    denominator = s0 * stt - st * st
    valid = (s0 >= 3) & (denominator > 1e-12 * np.maximum(s0 * stt, 1e-300))
    slope = np.where(valid, (s0 * sty - st * sy) / np.where(valid, denominator, 1.0), 0.0)
    return slope, valid
