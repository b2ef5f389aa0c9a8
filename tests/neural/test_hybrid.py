"""The NeuralFMU simulation against independent references: the analytic bouncing ball, fmubuilder's
engine on the plain FMU, and the untrained hybrid equal to the plain FMU."""
import math

import numpy as np
import pytest
import torch

from fmubuilder.neural import NeuralFMU, TopologyConfig, simulate
from fmubuilder.simulation import input_signals_from
from fmubuilder.neural.system import NumpyTopology, simulate_hybrid
from fmubuilder.simulation import simulate as engine_simulate

from .test_layer import unfolded_hybrid


def analytic_height(t, h0=1.0, e=0.7, g=9.81, v_min=0.1):
    """Height of the ball dropped from rest at h0 (examples/bouncing_ball/model.c)."""
    t_impact = math.sqrt(2 * h0 / g)
    if t < t_impact:
        return h0 - 0.5 * g * t * t
    v, t0 = g * t_impact, t_impact
    while True:
        v *= e
        if v < v_min:
            return 0.0
        if t < t0 + 2 * v / g:
            s = t - t0
            return v * s - 0.5 * g * s * s
        t0 += 2 * v / g


def test_bouncing_ball_rk4_is_exact(ball_fmu):
    """RK4 integrates the parabolas exactly; with located impacts the result is the analytic one."""
    with NeuralFMU(ball_fmu, TopologyConfig()) as model, torch.no_grad():
        run = simulate(model, 2.5, 0.01, record=["h"], solver="rk4")
    reference = np.array([analytic_height(t) for t in run.times])
    np.testing.assert_allclose(run.numpy("h")[:, 0], reference, atol=1e-9)
    assert run.stats["state_events"] >= 8


def random_gated_hybrid(path, channels, inputs, **kwargs):
    torch.manual_seed(3)
    model = NeuralFMU(path, TopologyConfig(channels=channels, inputs=inputs, hidden=[8, 8]), **kwargs)
    with torch.no_grad():
        for p in model.topology.ann.parameters():
            p.copy_(torch.randn_like(p))
    return model


@pytest.mark.parametrize("grad", [False, True])
def test_untrained_hybrid_equals_the_fmu_exactly(plant_fmu, grad):
    """Gates at (0, 1): bit-identical to the plain FMU in the same solver, with and without autograd,
    and equal to the engine's simulation of the FMU to round-off."""
    hybrid = random_gated_hybrid(plant_fmu, ["der(w)"], ["w", "der(w)", "u"])
    inputs = input_signals_from({"time": [0.0, 0.3, 0.301, 1.0], "setpoint": [1.0, 1.0, 2.0, 2.0]}, hybrid.info)
    plain = NeuralFMU(plant_fmu, TopologyConfig())
    with torch.set_grad_enabled(grad):
        a = simulate(hybrid, 1.0, 0.001, record=["w", "i", "u"], inputs=inputs, solver="rk4")
    with torch.no_grad():
        b = simulate(plain, 1.0, 0.001, record=["w", "i", "u"], inputs=inputs, solver="rk4")
    assert torch.equal(a.values.detach(), b.values)
    engine = engine_simulate(plant_fmu, stop_time=1.0, solver="rk4", step_size=0.001, output_interval=0.001,
                             inputs={"time": [0.0, 0.3, 0.301, 1.0], "setpoint": [1.0, 1.0, 2.0, 2.0]},
                             variables=["w", "i", "u"])
    for j, name in enumerate(["w", "i", "u"]):
        np.testing.assert_allclose(b.values[:, 0, j].numpy(), engine[name], rtol=1e-9, atol=1e-12)
    hybrid.close()
    plain.close()


def test_numpy_kernel_matches_torch(vldm_fmu):
    for activation in ["tanh", "sigmoid", "relu"]:
        model = NeuralFMU(vldm_fmu, TopologyConfig(channels=["der(speed)", "der(energy)"],
                                                   inputs=["speed", "der(speed)", "power"], hidden=[8, 4],
                                                   activation=activation))
        with torch.no_grad():
            for p in model.topology.parameters():
                p.copy_(torch.randn_like(p))
        kernel = NumpyTopology(model.topology)
        rng = np.random.default_rng(0)
        x, der, power = rng.normal(size=6), rng.normal(size=6), rng.normal(size=1)
        with torch.no_grad():
            expected = unfolded_hybrid(model.topology, torch.from_numpy(x)[None],
                                       torch.from_numpy(np.concatenate([der, power]))[None])
        np.testing.assert_allclose(kernel(x, der, power), expected[0].numpy(), rtol=1e-13, atol=1e-13)
        xs, ders, powers = rng.normal(size=(3, 6)), rng.normal(size=(3, 6)), rng.normal(size=(3, 1))
        with torch.no_grad():
            expected = unfolded_hybrid(model.topology, torch.from_numpy(xs),
                                       torch.from_numpy(np.concatenate([ders, powers], axis=1)))
        np.testing.assert_allclose(kernel.rows(xs, ders.copy(), powers), expected.numpy(), rtol=1e-13, atol=1e-13)
        model.close()


def test_engine_and_torch_solver_agree_on_an_active_hybrid(plant_fmu):
    """The same trained-looking hybrid (gate_ann = 0.3) in the engine (numpy kernel) and in the
    differentiable solver: same FMI semantics, same fixed-step RK4."""
    hybrid = random_gated_hybrid(plant_fmu, ["der(w)"], ["w", "der(w)"])
    with torch.no_grad():
        hybrid.topology.gate_ann.fill_(0.3)
        ours = simulate(hybrid, 1.0, 0.001, record=["w", "i", "der(w)"], solver="rk4",
                        inputs=input_signals_from({"time": [0.0, 1.0], "setpoint": [1.0, 1.0]}, hybrid.info))
    engine = simulate_hybrid(hybrid, start_time=0.0, stop_time=1.0, variables=["w", "i", "der(w)"], solver="rk4",
                             step_size=0.001, inputs=input_signals_from({"time": [0.0, 1.0], "setpoint": [1.0, 1.0]},
                                                                       hybrid.info))
    for j, name in enumerate(["w", "i", "der(w)"]):
        np.testing.assert_allclose(ours.values[:, 0, j].numpy(), engine[name], rtol=1e-9, atol=1e-10)
    plain = engine_simulate(plant_fmu, stop_time=1.0, solver="rk4", step_size=0.001, output_interval=0.001,
                            inputs={"time": [0.0, 1.0], "setpoint": [1.0, 1.0]}, variables=["w"])
    assert np.abs(plain["w"] - engine["w"]).max() > 1e-3  # the ANN does change the dynamics
    hybrid.close()


def test_hybrid_derivatives_recorded_at_termination():
    """The corner-case FMU asks to terminate at a time event; the last output row is then read in
    event mode, where the FMU refuses new states. The recorded hybrid derivative there must still
    be the network applied to the FMU's own derivative (the torch topology as reference)."""
    from fmubuilder.build import example_fmu
    hybrid = random_gated_hybrid(example_fmu("event_corner_cases"), ["der(r)"], ["r"])
    with torch.no_grad():
        hybrid.topology.gate_ann.fill_(0.3)
    names = ["p", "r", "der(p)", "der(r)"]
    result = simulate_hybrid(hybrid, start_time=0.0, stop_time=5.0, variables=names, solver="euler", step_size=0.01)
    plain = engine_simulate(example_fmu("event_corner_cases"), stop_time=5.0, solver="euler", step_size=0.01,
                            output_interval=0.01, variables=["der(p)", "der(r)"])
    assert result["time"][-1] == pytest.approx(3.5)      # terminated by the model
    x = torch.tensor([[result["p"][-1], result["r"][-1]]])
    der_fmu = torch.tensor([[plain["der(p)"][-1], plain["der(r)"][-1]]])
    with torch.no_grad():
        expected = unfolded_hybrid(hybrid.topology, x, der_fmu)[0].numpy()
    np.testing.assert_allclose([result["der(p)"][-1], result["der(r)"][-1]], expected, rtol=1e-12, atol=1e-12)
    assert abs(result["der(r)"][-1] - plain["der(r)"][-1]) > 1e-3     # the network does act there
    hybrid.close()
