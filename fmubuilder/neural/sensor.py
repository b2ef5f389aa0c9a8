"""What the sensors show at the data's samples, read from a differentiable run (solve.Trajectory).

The choice's scoring reads an engine run recorded on both sides of every event
(data.sensor_reading: the first-order lag of an input linear between the records, then the value
at a sample, the settled one at an event's time). The training reads its torch run the same way:
with RK4 the run records each grid point after its events (`values`) and before them (`before`),
and the steps of an interval that an event cuts (`inner`). Read from the grid points after their
events alone, a signal that a sampled controller moves in steps (the VLDM's power jumps at every
10 ms tick while the car accelerates) was taken for a ramp from one step to the next, half a step
early: on the extra resistance's truth the training's loss read 1.49 times the noise variance on
the power where the scoring reads 1.06 (docs/MEASUREMENTS.md, "The training's loss at the truth").
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch


@dataclass
class SensorGrid:
    """One signal of a run as its sensor shows it on the grid (see sensor_grid)."""
    shown: torch.Tensor        # [K+1, B]: through the lag; without one, the values after the events
    before: torch.Tensor | None  # [K, B]: without a lag, the value at grid point k + 1 before its events
    cut: dict                  # without a lag, {(k, b): [(start, end, value at start, value at end)]}
    step: float

    def read(self, b: int, k0: torch.Tensor, frac: torch.Tensor) -> torch.Tensor:
        """Element b's sensor at t0 + (k0 + frac) step, linear between the records, the settled value
        at an event's time."""
        column = self.shown[:, b]
        end = column[k0 + 1]
        if self.before is not None:   # no lag: towards the value before the events at k0 + 1
            end = torch.where(frac >= 1.0, end, self.before[:, b][k0])   # the last grid point: settled
        reading = column[k0] * (1.0 - frac) + end * frac
        cut = [(i, self.cut[(int(k), b)]) for i, k in enumerate(k0.tolist()) if (int(k), b) in self.cut]
        if not cut:
            return reading
        within = [_within_steps(steps, (float(k0[i]) + float(frac[i])) * self.step) for i, steps in cut]
        return reading.index_put((torch.tensor([i for i, _ in cut]),), torch.stack(within))


def sensor_grid(trajectory, j: int, lag: float, shown: torch.Tensor | None = None) -> SensorGrid:
    """Recorded variable j of `trajectory` as a sensor with a first-order lag `lag` shows it: the
    output of `lag * dy/dt = u - y` for u linear between the records (data.first_order_lag), starting
    at the run's first value, or at `shown` [B] (what the data show there), the difference decaying
    with the lag (a sensor assumed settled made every element of a ramp or a heating start with an
    error of the lag times the slope, which on the DC drive outweighed the missing term). Without
    `before` (Euler) the grid points' values are read as if no event lay between them."""
    post = trajectory.values[:, :, j]
    before = trajectory.before[:, :, j] if trajectory.before is not None else post[1:]
    cut = {(k, b): [(s0, s1, u0[j], u1[j]) for s0, s1, u0, u1 in steps] for k, b, steps in trajectory.inner}
    times = np.asarray(trajectory.times, dtype=float)
    step = float(times[1] - times[0]) if len(times) > 1 else 0.0
    if lag <= 0.0:
        return SensorGrid(post, before, cut, step)
    lagged = _lagged(post, before, cut, times, lag)
    if shown is not None:
        decay = torch.exp(-torch.from_numpy(times - times[0]) / lag)
        lagged = lagged + decay[:, None] * (shown - post[0])[None, :]
    cut_lagged = {}
    for (k, b), steps in cut.items():     # the lagged output at the events inside the interval
        y, shown_steps = lagged[k, b], []
        for start, stop, u0, u1 in steps:
            a, ramp = _gains(stop - start, lag)
            y_next = a * y + (1.0 - a) * u0 + ramp * (u1 - u0)   # (a start's offset decays alike)
            shown_steps.append((start, stop, y, y_next))
            y = y_next
        cut_lagged[(k, b)] = shown_steps
    return SensorGrid(lagged, None, cut_lagged, step)


def _lagged(post, before, cut, times, lag) -> torch.Tensor:
    """y[k + 1] = a y[k] + g[k] with y[0] = post[0]: g is what the input adds over interval k, from
    its value after the events at k to the one before the events at k + 1 (from each step's ends
    where events cut it). A convolution with a^m, cut where the memory falls below 1e-12."""
    h = float(times[1] - times[0])
    a, ramp = _gains(h, lag)
    g = (1.0 - a - ramp) * post[:-1] + ramp * before
    if cut:
        end = {(k, b): float(times[k + 1]) for k, b in cut}
        keys = list(cut)
        g = g.index_put((torch.tensor([k for k, _ in keys]), torch.tensor([b for _, b in keys])),
                        torch.stack([_added(steps, end[key], lag) for key, steps in cut.items()]))
    taps = int(math.ceil(math.log(1e-12) / math.log(a))) + 1
    memory = torch.from_numpy(a ** np.arange(taps))
    settled = ((1.0 - a) * post[0]).expand(taps - 1, -1)      # the input held at its first value before
    padded = torch.cat([settled, g], dim=0)
    y = torch.nn.functional.conv1d(padded.T.unsqueeze(1), memory.flip(0).view(1, 1, -1)).squeeze(1).T
    lagged = torch.cat([post[:1], y], dim=0)
    last = float(times[-1] - times[-2])
    if abs(last - h) > 1e-9 * h:     # a run whose duration is no multiple of the step: a shorter last interval
        a_last, ramp_last = _gains(last, lag)
        fixed = a_last * lagged[-2] + (1.0 - a_last - ramp_last) * post[-2] + ramp_last * before[-1]
        if cut:
            fixed = torch.stack([_added(cut[(len(times) - 2, b)], float(times[-1]), lag) + a_last * lagged[-2, b]
                                 if (len(times) - 2, b) in cut else fixed[b] for b in range(post.shape[1])])
        lagged = torch.cat([lagged[:-1], fixed[None]], dim=0)
    return lagged


def _gains(h: float, lag: float) -> tuple[float, float]:
    """(decay over h, the weight of the input's change over h) of the lag for an input linear over h."""
    return math.exp(-h / lag), 1.0 - lag / h * -math.expm1(-h / lag) if h > 1e-12 * lag else 0.0


def _added(steps, end: float, lag: float) -> torch.Tensor:
    """What an interval made of `steps` (each linear from its start's value to its end's, a jump
    between them) adds to the lagged output at `end`."""
    total = 0
    for start, stop, u0, u1 in steps:
        a, ramp = _gains(stop - start, lag)
        total = total + math.exp(-(end - stop) / lag) * ((1.0 - a) * u0 + ramp * (u1 - u0))
    return total


def _within_steps(steps, t: float) -> torch.Tensor:
    """The value at t of an interval made of `steps`: linear within a step, the settled value (the
    next step's start) at an event's time."""
    for start, stop, u0, u1 in steps:
        if t < stop:
            return u0 + (u1 - u0) * ((t - start) / (stop - start))
    start, stop, u0, u1 = steps[-1]
    return u1
