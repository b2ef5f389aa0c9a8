"""A NeuralFMU simulated by the compiled core (its network and base term evaluated in C, inside the
loop) against the same engine with the Python loop (FMUBUILDER_ENGINE=python), which evaluates the
network in numpy: the same trajectories to round-off (the two sum dot products in different orders),
the same events and counts, on models with state, time and step events, inputs, several channels,
FMU variables as inputs, each activation, and a fitted base term."""
import numpy as np
import pytest
import torch

from fmubuilder.build import example_fmu
from fmubuilder.neural import NeuralFMU, TopologyConfig
from fmubuilder.neural.system import simulate_hybrid
from fmubuilder.simulation import core
from fmubuilder.simulation.inputs import input_signals_from

CASES = {
    "ball, one channel": ("bouncing_ball", TopologyConfig(channels=["der(v)"], inputs=["h", "v"], hidden=[8, 8]),
                          ["h", "v", "der(v)"], 3.0, None),
    "plant with inputs, FMU variable and derivative in": (
        "sampled_plant", TopologyConfig(channels=["der(w)"], inputs=["w", "der(w)", "u"], hidden=[6],
                                        activation="sigmoid"),
        ["w", "i", "u", "der(w)"], 2.0, {"time": [0.0, 0.5, 0.51, 2.0], "setpoint": [1.0, 1.0, 2.0, -1.0]}),
    "VLDM, two channels, relu": (
        "vldm", TopologyConfig(channels=["der(speed)", "der(energy)"], inputs=["speed", "power"], hidden=[8, 4],
                               activation="relu"),
        ["speed", "energy", "power", "der(speed)"], 30.0, None),
    "DC drive with a base term": (
        "dc_drive", TopologyConfig(channels=["der(speed)"], inputs=["speed"], hidden=[8], kind="residual",
                                   base_terms=[{"variable": "speed", "basis": "w*|w|", "center": 0.0,
                                                "coefficient": -0.002},
                                               {"variable": "speed", "basis": "w", "center": 1.0,
                                                "coefficient": -0.01}]),
        ["speed", "current", "energy"], 5.0, None),
    "event corner cases, terminating": (
        "event_corner_cases", TopologyConfig(channels=["der(r)"], inputs=["r", "p"], hidden=[4]),
        ["p", "r", "der(p)", "der(r)"], 5.0, None),
}


def random_hybrid(name, config):
    torch.manual_seed(7)
    model = NeuralFMU(example_fmu(name), config)
    with torch.no_grad():
        for p in model.topology.ann.parameters():
            p.copy_(0.3 * torch.randn_like(p))
        model.topology.gate_ann.fill_(0.5)
    return model


@pytest.mark.parametrize("solver", ["euler", "rk4"])
@pytest.mark.parametrize("case", sorted(CASES))
def test_the_compiled_network_runs_the_numpy_one(monkeypatch, case, solver):
    name, config, variables, stop, inputs = CASES[case]
    model = random_hybrid(name, config)
    options = dict(start_time=0.0, stop_time=stop, variables=variables, solver=solver, step_size=0.005,
                   record_events=True)
    signals = input_signals_from(inputs, model.info) if inputs else None
    try:
        monkeypatch.setenv("FMUBUILDER_ENGINE", "python")
        python = simulate_hybrid(model, inputs=signals, **options)
        monkeypatch.delenv("FMUBUILDER_ENGINE")
        compiled = simulate_hybrid(model, inputs=signals, **options)
    finally:
        model.close()
    assert [kind for _, kind in compiled.events] == [kind for _, kind in python.events]
    np.testing.assert_allclose([t for t, _ in compiled.events], [t for t, _ in python.events], rtol=0, atol=1e-9)
    np.testing.assert_allclose(compiled.time, python.time, rtol=0, atol=1e-9)
    for variable in variables:
        scale = max(1.0, float(np.abs(python[variable]).max()))
        np.testing.assert_allclose(compiled[variable], python[variable], rtol=0, atol=1e-9 * scale, err_msg=variable)
    for count in ("steps", "rhs_evaluations", "time_events", "state_events", "step_events"):
        assert getattr(compiled.stats, count) == getattr(python.stats, count), count


def test_the_core_takes_the_network_and_leaves_other_systems_to_python():
    """A NeuralFMU system runs in the core; a subclass that changes the derivatives in Python only
    does not; an untrained NeuralFMU (the network gated off) is the plain FMU there."""
    from fmubuilder.neural.system import NeuralFmuSystem
    from fmubuilder.simulation.solvers import DOPRI5, RK4
    model = random_hybrid("bouncing_ball", CASES["ball, one channel"][1])

    class Shifted(NeuralFmuSystem):
        def derivatives(self, t, x):
            return super().derivatives(t, x) + 1.0

    try:
        system = NeuralFmuSystem(model, variables=["h"])
        shifted = Shifted(model, variables=["h"])
        assert core.applies(system, RK4(0.01)) and core.applies(system, DOPRI5())
        assert not core.applies(system, DOPRI5(first_step=1e-3))
        assert system.compiled_correction() is not None
        assert not core.applies(shifted, RK4(0.01))
        with torch.no_grad():
            model.topology.gate_ann.fill_(0.0)
        assert NeuralFmuSystem(model, variables=["h"]).compiled_correction() is None
        for s in (system, shifted):
            s.close()
    finally:
        model.close()
