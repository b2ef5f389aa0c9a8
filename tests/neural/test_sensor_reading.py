"""The training reads its differentiable run as the choice's scoring reads an engine run: through the
sensors' first-order lag of an input linear between the records, both sides of every event, the
settled value at an event's time (data.sensor_reading).

sampled_plant's controller holds its output `u` for 10 ms, so `u` is a staircase, and on a 4 ms
grid its steps fall between grid points (0.01, 0.03, ...) and on them (0.02, 0.04, ...)."""
import numpy as np
import pytest
import torch

from fmubuilder.data import sensor_reading
from fmubuilder.neural import NeuralFMU, TopologyConfig, simulate
from fmubuilder.neural.sensor import sensor_grid
from fmubuilder.neural.solve import Trajectory
from fmubuilder.simulation import input_signals_from
from fmubuilder.simulation import simulate as engine_simulate

NAMES = ["w", "i", "u"]
STEP, STOP = 0.004, 0.1


def _samples(step: float, count: int):
    """(k0, frac, time) of samples 1 ms apart, 0.3 ms off every grid point and every event."""
    times = 0.0003 + 0.001 * np.arange(count)
    position = times / step
    k0 = np.floor(position).astype(int)
    return torch.from_numpy(k0), torch.from_numpy(position - k0), times


@pytest.mark.parametrize("lag", [0.0, 0.003, 0.02])
def test_the_training_reads_a_sampled_staircase_as_the_scoring_does(plant_fmu, lag):
    setpoint = {"time": [0.0, 0.05, 0.0501, 1.0], "setpoint": [1.0, 1.0, -0.5, -0.5]}
    engine = engine_simulate(plant_fmu, stop_time=STOP, solver="rk4", step_size=STEP, output_interval=STEP,
                             inputs=setpoint, variables=NAMES, record_events=True)
    with NeuralFMU(plant_fmu, TopologyConfig()) as model, torch.no_grad():
        run = simulate(model, STOP, STEP, record=NAMES, solver="rk4",
                       inputs=input_signals_from(setpoint, model.info))
    assert run.inner, "the grid intervals with a controller sample inside are cut into steps"
    k0, frac, times = _samples(STEP, 99)
    for j, name in enumerate(NAMES):
        expected = sensor_reading(engine.time, engine[name], times, lag)
        ours = sensor_grid(run, j, lag).read(0, k0, frac).numpy()
        scale = np.max(np.abs(engine[name]))
        np.testing.assert_allclose(ours, expected, rtol=0, atol=1e-9 * scale)
    # the staircase read from the grid points alone (as before): off by up to a step of u
    grid_only = Trajectory(run.times, run.t0, run.names, run.values, run.final_states)
    j = NAMES.index("u")
    off = sensor_grid(grid_only, j, lag).read(0, k0, frac).numpy() - sensor_reading(engine.time, engine["u"], times, lag)
    assert np.max(np.abs(off)) > 0.05 * np.max(np.abs(np.diff(engine["u"])))


def test_a_step_inside_an_interval_lags_as_the_analytic_step_response():
    """An input 0 that steps to 1 at 0.0137 (inside the interval 0.01-0.02), then stays: the sensor
    shows 1 - exp(-(t - 0.0137) / lag) after it, exactly at the records (the grid points and the
    event), linear between them (as the scoring reads an engine run)."""
    h, lag, t_e = 0.01, 0.02, 0.0137
    grid = np.arange(0.0, 0.1 + h / 2, h)
    K = len(grid) - 1
    post = torch.zeros(K + 1, 1, 1, dtype=torch.float64)
    post[2:] = 1.0
    before = post[1:].clone()
    before[0] = 0.0                              # interval 0: no event; interval 1: cut at t_e
    inner = [(1, 0, [(0.01, t_e, torch.zeros(1, dtype=torch.float64), torch.zeros(1, dtype=torch.float64)),
                     (t_e, 0.02, torch.ones(1, dtype=torch.float64), torch.ones(1, dtype=torch.float64))])]
    run = Trajectory(grid, np.zeros(1), ["u"], post, torch.zeros(1, 1), None, {}, {}, before, inner)
    times = np.array([0.005, 0.012, t_e, 0.015, 0.02, 0.0333, 0.0871])
    position = times / h
    k0 = np.minimum(np.floor(position + 1e-12).astype(int), K - 1)
    records = np.sort(np.append(grid, t_e))
    analytic = np.interp(times, records, np.where(records >= t_e, -np.expm1(-(records - t_e) / lag), 0.0))
    ours = sensor_grid(run, 0, lag).read(0, torch.from_numpy(k0), torch.from_numpy(position - k0)).numpy()
    np.testing.assert_allclose(ours, analytic, atol=1e-12)
    settled = sensor_grid(run, 0, 0.0).read(0, torch.from_numpy(k0), torch.from_numpy(position - k0)).numpy()
    np.testing.assert_array_equal(settled, (times >= t_e).astype(float))


def test_a_ramp_through_the_lag_matches_the_analytic_response():
    """A ramp u = t from a settled start: t - lag (1 - exp(-t/lag)); an element entering mid-ramp
    whose sensor shows t0 - lag: t - lag from the start on (a settled start errs by lag * slope)."""
    h, lag = 0.01, 0.1
    for t0, shown in [(0.0, None), (2.0, 2.0 - lag)]:
        t = np.arange(t0, t0 + 3.0, h)
        ramp = torch.from_numpy(np.stack([t, -2.0 * t], axis=1))[:, :, None].permute(0, 2, 1)  # [K+1, 1, 2]
        run = Trajectory(t - t0, np.array([t0]), ["a", "b"], ramp, torch.zeros(1, 2), before=None)
        analytic = t - lag * (1.0 - np.exp(-(t - t0) / lag)) if shown is None else t - lag
        for j, factor in enumerate([1.0, -2.0]):
            start = None if shown is None else torch.tensor([factor * shown], dtype=torch.float64)
            seen = sensor_grid(run, j, lag, start).shown[:, 0].numpy()
            np.testing.assert_allclose(seen, factor * analytic, atol=1e-10)
