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
