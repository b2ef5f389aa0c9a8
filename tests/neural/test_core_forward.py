"""Runs without gradient in the compiled core (core_gradient.simulate_without_gradient) against the
torch batch solver (solve.simulate), an independent implementation of the same event semantics: the
VLDM (state events, held discrete states, time events every step) and the bouncing ball (state
resets), with the network in the loop, split at captured grid points and continued from them."""
import numpy as np
import pytest
import torch

from fmubuilder.build import example_fmu
from fmubuilder.neural.core_gradient import runs_in_core, simulate_without_gradient
from fmubuilder.neural.model import NeuralFMU
from fmubuilder.neural.solve import ElementStart, simulate
from fmubuilder.neural.topology import TopologyConfig

CASES = {  # example: (channel, ANN input, recorded, span in s, captured grid points)
    "vldm": ("der(speed)", "speed", ["speed", "energy", "der(speed)", "power"], 60.0, [0, 1500, 4000, 6000]),
    "bouncing_ball": ("der(v)", "v", ["h", "v", "der(v)"], 3.0, [0, 120, 300]),
}


def perturbed_model(example: str) -> NeuralFMU:
    channel, ann_input, *_ = CASES[example]
    torch.manual_seed(0)
    model = NeuralFMU(example_fmu(example), TopologyConfig(channels=[channel], inputs=[ann_input], hidden=[8, 8]))
    with torch.no_grad():
        for parameter in model.topology.ann.parameters():
            parameter.add_(0.1 * torch.randn_like(parameter))
    return model


def relative_difference(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().max() / max(float(a.abs().max()), 1e-12))


@pytest.mark.parametrize("solver", ["rk4", "euler"])
@pytest.mark.parametrize("example", sorted(CASES))
def test_a_split_run_in_the_core_agrees_with_the_torch_solver(example, solver):
    model = perturbed_model(example)
    assert runs_in_core(model)
    _, _, record, span, capture = CASES[example]
    with torch.no_grad():
        ours = simulate_without_gradient(model, span, 0.01, starts=[ElementStart(0.0)], record=record, solver=solver,
                                         capture=capture)
        torch_run = simulate(model, span, 0.01, starts=[ElementStart(0.0)], record=record, solver=solver,
                             capture=capture)
    assert ours.stats.get("core_gradient") and not torch_run.stats.get("core_gradient")
    np.testing.assert_allclose(ours.times, torch_run.times, rtol=0, atol=1e-9)
    assert relative_difference(ours.values, torch_run.values) < 1e-7
    assert sorted(ours.captured) == sorted(torch_run.captured) == capture
    for k in capture:
        assert ours.captured[k][0].t0 == pytest.approx(torch_run.captured[k][0].t0, abs=1e-9)
    if solver == "rk4":
        assert relative_difference(ours.before, torch_run.before) < 1e-7
        assert [(k, len(steps)) for k, _, steps in ours.inner] == [(k, len(steps)) for k, _, steps in torch_run.inner]
    # elements started from the captured states, side by side
    starts = [[run.captured[k][0] for k in capture[1:3]] for run in (ours, torch_run)]
    with torch.no_grad():
        elements = simulate_without_gradient(model, span / 4, 0.01, starts=starts[0], record=record, solver=solver)
        reference = simulate(model, span / 4, 0.01, starts=starts[1], record=record, solver=solver)
    assert relative_difference(elements.values, reference.values) < 1e-7


def test_a_model_with_trained_fmu_parameters_stays_with_torch():
    model = NeuralFMU(example_fmu("bouncing_ball"), TopologyConfig(channels=["der(v)"], inputs=["v"], hidden=[4],
                                                                 parameters=["e"]))
    assert not runs_in_core(model)
    with torch.no_grad():
        run = simulate_without_gradient(model, 0.5, 0.01, starts=[ElementStart(0.0)], record=["h"], solver="rk4")
    assert not run.stats.get("core_gradient") and run.values.shape == (51, 1, 1)
