"""fmi2CompletedIntegratorStep in the differentiable solver: after every accepted step, the step cut
at a state event included, as fmubuilder's engine (an independent driver of the same FMU) calls it.

The test FMU (completed_steps/) counts the calls, and only a completed step at or after
t_step = 0.93 requests its step event, which turns the ramp r: the step cut at the state event at
p_max = 0.95 is the first such step, so r turns at 0.95 (analytic), not at the next grid point."""
from pathlib import Path

import numpy as np
import pytest
import torch

from fmubuilder.build import build_cmake_project
from fmubuilder.neural import NeuralFMU, TopologyConfig, simulate
from fmubuilder.simulation import simulate as engine_simulate

HERE = Path(__file__).resolve().parent
NAMES = ["p", "r", "steps", "step_event_time"]
P_MAX, STEP, STOP = 0.95, 0.1, 2.0


@pytest.fixture(scope="module")
def completed_steps_fmu(tmp_path_factory):
    build = build_cmake_project(HERE / "completed_steps", tmp_path_factory.mktemp("completed_steps_build"))
    return build.build_dir / "fmus" / "completed_steps.fmu"


def analytic_r(t, t_turn=P_MAX):
    return np.where(t < t_turn, t, 2 * t_turn - t)


@pytest.mark.parametrize("solver", ["euler", "rk4"])
@pytest.mark.parametrize("grad", [False, True])
def test_a_step_cut_at_a_state_event_is_a_completed_step(completed_steps_fmu, solver, grad):
    engine = engine_simulate(completed_steps_fmu, stop_time=STOP, solver=solver, step_size=STEP,
                             output_interval=STEP, variables=NAMES)
    with NeuralFMU(completed_steps_fmu, TopologyConfig()) as model, torch.set_grad_enabled(grad):
        x0 = torch.zeros(1, 2, dtype=torch.float64, requires_grad=grad)
        run = simulate(model, STOP, STEP, record=NAMES, solver=solver, x0=x0)
    assert run.times.size == engine.time.size
    np.testing.assert_allclose(run.t0[0] + run.times, engine.time, atol=1e-12)
    # the engine against the analytic answer, then the torch solver against the engine
    assert engine["step_event_time"][-1] == pytest.approx(P_MAX, abs=1e-9)
    np.testing.assert_allclose(engine["r"], analytic_r(engine.time), atol=1e-9)
    np.testing.assert_allclose(run.numpy("step_event_time")[:, 0], engine["step_event_time"], atol=1e-9)
    np.testing.assert_allclose(run.numpy("r")[:, 0], engine["r"], atol=1e-9)
    np.testing.assert_allclose(run.numpy("p")[:, 0], engine["p"], atol=1e-9)
    # every completed step: 20 grid steps and the step cut at 0.95 (the second reset, at 1.9, is
    # on the grid: its step ends there, no extra step)
    np.testing.assert_array_equal(run.numpy("steps")[:, 0], engine["steps"])
    assert engine["steps"][-1] == round(STOP / STEP) + 1
    assert run.stats["step_events"] == engine.stats.step_events == 1
    assert run.stats["state_events"] == engine.stats.state_events == 2


@pytest.mark.parametrize("solver", ["euler", "rk4"])
def test_a_batch_element_steps_as_if_alone(plant_fmu, solver):
    """Each element steps to its own limits: starts whose controller samples (time events every
    10 ms) fall at different points of the 4 ms grid step give each element of a batch the
    trajectory of its run alone, and the fresh start the engine's trajectory of the same FMU."""
    from fmubuilder.neural.solve import ElementStart
    from fmubuilder.simulation import input_signals_from
    setpoint = {"time": [0.0, 1.0], "setpoint": [1.0, 1.0]}
    names = ["w", "i", "u"]
    with NeuralFMU(plant_fmu, TopologyConfig()) as model, torch.no_grad():
        inputs = input_signals_from(setpoint, model.info)
        lead = simulate(model, 0.012, 0.004, inputs=inputs, capture=[1, 2], solver=solver)
        starts = [ElementStart(0.0)] + lead.captured[1] + lead.captured[2]
        batch = simulate(model, 0.1, 0.004, starts=starts, record=names, inputs=inputs, solver=solver)
        for b, start in enumerate(starts):
            alone = simulate(model, 0.1, 0.004, starts=[start], record=names, inputs=inputs, solver=solver)
            np.testing.assert_allclose(batch.values[:, b].numpy(), alone.values[:, 0].numpy(), rtol=1e-12, atol=0)
    engine = engine_simulate(plant_fmu, stop_time=0.1, solver=solver, step_size=0.004, output_interval=0.004,
                             inputs=setpoint, variables=names)
    for j, name in enumerate(names):
        np.testing.assert_allclose(batch.values[:, 0, j].numpy(), engine[name], rtol=1e-9, atol=1e-12)


def test_gradients_of_a_batch_element_with_its_own_time_events(plant_fmu):
    """The same batch with gradients: each element's gradient with respect to its initial state is
    that of its run alone, and matches central differences of the batch simulation."""
    from fmubuilder.neural.solve import ElementStart
    from fmubuilder.simulation import input_signals_from
    with NeuralFMU(plant_fmu, TopologyConfig()) as model:
        inputs = input_signals_from({"time": [0.0, 1.0], "setpoint": [1.0, 1.0]}, model.info)
        with torch.no_grad():
            lead = simulate(model, 0.008, 0.004, inputs=inputs, capture=[1])
        starts = [ElementStart(0.0)] + lead.captured[1]
        x0 = torch.tensor([[0.1, 0.2], [0.3, 0.1]], dtype=torch.float64, requires_grad=True)

        def final_speed(x0_rows, rows):
            run = simulate(model, 0.06, 0.004, starts=[starts[b] for b in rows], x0=x0_rows, record=["w"],
                           inputs=inputs, solver="rk4")
            return run.signal("w")[-1]

        final_speed(x0, [0, 1]).sum().backward()
        for b in range(2):
            alone = x0[b:b + 1].detach().clone().requires_grad_(True)
            final_speed(alone, [b]).sum().backward()
            np.testing.assert_allclose(x0.grad[b].numpy(), alone.grad[0].numpy(), rtol=1e-12)
            for j in range(2):
                delta = 1e-6
                with torch.no_grad():
                    plus, minus = x0.detach().clone(), x0.detach().clone()
                    plus[b, j] += delta
                    minus[b, j] -= delta
                    fd = (final_speed(plus, [0, 1])[b] - final_speed(minus, [0, 1])[b]) / (2 * delta)
                assert x0.grad[b, j].item() == pytest.approx(fd.item(), rel=1e-4, abs=1e-8)


def test_a_time_event_a_rounding_error_past_a_grid_point_as_the_engine_decides(plant_fmu):
    """One time tolerance for both drivers: with the sample period 4e-12 longer than the grid step,
    the samples fall 4e-12 t past the grid points, within the tolerance (1e-12 of the time scale,
    here the stop time 0.5) up to t = 0.125 and beyond it after: there each a step of its own. The
    torch solver takes the engine's steps and events, and its trajectory (up to its steps to a time
    event within the tolerance past a grid point, which the engine ends at the grid point)."""
    period, stop = 0.01 * (1 + 4e-12), 0.5
    setpoint = {"time": [0.0, 1.0], "setpoint": [1.0, 1.0]}
    names = ["w", "i", "u"]
    engine = engine_simulate(plant_fmu, stop_time=stop, solver="euler", step_size=0.01, output_interval=0.01,
                             inputs=setpoint, variables=names, start_values={"Ts": period})
    from fmubuilder.simulation import input_signals_from
    with NeuralFMU(plant_fmu, TopologyConfig(), start_values={"Ts": period}) as model, torch.no_grad():
        run = simulate(model, stop, 0.01, record=names, inputs=input_signals_from(setpoint, model.info),
                       solver="euler")
    # samples k Ts: k = 0 at the initialization, 1..49 time events, the 50th past the stop; a step
    # of its own to each of k = 13..49 (past 0.125)
    assert engine.stats.time_events == 49 and engine.stats.steps == 50 + 37
    assert run.stats["steps"] == engine.stats.steps and run.stats["time_events"] == engine.stats.time_events
    for j, name in enumerate(names):
        np.testing.assert_allclose(run.values[:, 0, j].numpy(), engine[name], rtol=1e-9, atol=1e-12)
