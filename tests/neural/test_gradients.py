"""Gradients across events against central finite differences of the whole simulation
(same solver, same fixed step): state events with resets (bouncing ball), time events of a
sampled PI controller with a discrete integrator (sampled_plant), and a closed-loop VLDM run
where the effect of the ANN on the energy goes through the sampled driver."""
import numpy as np
import pytest
import torch

from fmubuilder.neural import NeuralFMU, TopologyConfig, simulate
from fmubuilder.neural.layer import EventSensitivity
from fmubuilder.simulation import input_signals_from

STEP = 1e-6  # relative step of the central differences of the whole simulation


def central_difference(f, tensor, index, step=STEP):
    """d f / d tensor[index] with f evaluated without gradients."""
    base = float(tensor[index])
    delta = step * max(1.0, abs(base))
    with torch.no_grad():
        tensor[index] = base + delta
        plus = f()
        tensor[index] = base - delta
        minus = f()
        tensor[index] = base
    return (plus - minus) / (2 * delta)


@pytest.mark.parametrize("solver, step", [("rk4", 0.01), ("euler", 0.001)])
def test_bouncing_ball_across_impacts(ball_fmu, solver, step):
    """h(T) + 0.3 v(T) after three impacts: gradient w.r.t. h0 and the restitution e."""
    model = NeuralFMU(ball_fmu, TopologyConfig(parameters=["e"]))
    x0 = torch.tensor([[1.0, 0.0]], dtype=torch.float64, requires_grad=True)
    e = model.topology.fmu_parameters

    def objective():
        run = simulate(model, 1.7, step, x0=x0, record=["h", "v"], solver=solver)
        return run.signal("h")[-1, 0] + 0.3 * run.signal("v")[-1, 0], run

    value, run = objective()
    assert run.stats["state_events"] == 3
    value.backward()
    fd_h0 = central_difference(lambda: float(objective()[0]), x0.data, (0, 0))
    fd_e = central_difference(lambda: float(objective()[0]), e.data, 0)
    assert x0.grad[0, 0].item() == pytest.approx(fd_h0, rel=1e-3)
    assert e.grad[0].item() == pytest.approx(fd_e, rel=1e-3)
    # the restitution acts only in the reset map: without event gradients it would be zero
    assert abs(fd_e) > 1.0
    model.close()


def test_sampled_controller_with_discrete_integrator(plant_fmu):
    """Across 50 controller samples: gradients w.r.t. the initial state and the tunable gain Kp.
    The controller's integral is a discrete state with memory, so this needs the shadow states."""
    model = NeuralFMU(plant_fmu, TopologyConfig(parameters=["Kp"]))
    inputs = input_signals_from({"time": [0.0, 10.0], "setpoint": [1.0, 1.0]}, model.info)
    x0 = torch.tensor([[0.0, 0.2]], dtype=torch.float64, requires_grad=True)
    kp = model.topology.fmu_parameters

    def objective():
        run = simulate(model, 0.5, 0.002, x0=x0, record=["w", "i"], solver="rk4", inputs=inputs)
        return run.signal("w")[-1, 0] + run.signal("i")[-1, 0], run

    value, run = objective()
    assert run.stats["time_events"] == 50
    value.backward()
    for index in [(0, 0), (0, 1)]:
        fd = central_difference(lambda: float(objective()[0]), x0.data, index)
        assert x0.grad[index].item() == pytest.approx(fd, rel=1e-3, abs=1e-6)
    fd_kp = central_difference(lambda: float(objective()[0]), kp.data, 0)
    assert kp.grad[0].item() == pytest.approx(fd_kp, rel=1e-3)
    model.close()


def test_ann_weights_in_a_batch(plant_fmu):
    """Two elements side by side from saved FMU states; gradient of a data-like loss w.r.t. ANN
    weights (residual topology on der(w), inputs w and der(w))."""
    torch.manual_seed(1)
    model = NeuralFMU(plant_fmu, TopologyConfig(channels=["der(w)"], inputs=["w", "der(w)"], hidden=[6],
                                                 kind="residual"))
    with torch.no_grad():
        for p in model.topology.ann.parameters():
            p.copy_(0.3 * torch.randn_like(p))
    inputs = input_signals_from({"time": [0.0, 0.6, 0.601, 3.0], "setpoint": [1.0, 1.0, 2.0, 2.0]}, model.info)
    with torch.no_grad():
        reference = simulate(model, 1.0, 0.002, record=["w"], inputs=inputs, capture=[100, 300])
    starts = [reference.captured[100][0], reference.captured[300][0]]
    starts[1].states = {"w": 0.9}
    target = torch.linspace(0.5, 2.0, 201, dtype=torch.float64)[:, None]

    def objective():
        run = simulate(model, 0.4, 0.002, starts=starts, record=["w"], inputs=inputs)
        return ((run.signal("w") - target) ** 2).mean()

    objective().backward()
    for layer, index in [(0, (2, 1)), (2, (0, 3))]:
        weight = model.topology.ann[layer].weight
        fd = central_difference(lambda: float(objective()), weight.data, index)
        assert weight.grad[index].item() == pytest.approx(fd, rel=2e-3)
    model.close()


def test_closed_loop_energy_through_the_driver(vldm_fmu):
    """VLDM, 20 s of driving: an extra force on der(speed) changes the energy only because the
    sampled driver reacts to the speed. The gradient w.r.t. the ANN's output bias matches the finite
    difference; without the discrete-state path it has the wrong sign."""
    model = NeuralFMU(vldm_fmu, TopologyConfig(channels=["der(speed)"], inputs=["speed"], hidden=[4],
                                               kind="residual"), start_values={"cycle": 1})
    with torch.no_grad():
        reference = simulate(model, 60.0, 0.01, record=["speed"], capture=[4000])
    start = reference.captured[4000][0]
    assert reference.numpy("speed")[4000, 0] > 1.0  # moving
    bias = model.topology.ann[-1].bias

    def objective(event_gradients=True):
        run = simulate(model, 20.0, 0.01, starts=[start], record=["energy"], event_gradients=event_gradients)
        return run.signal("energy")[-1, 0] / 1e3

    objective().backward()
    gradient = bias.grad[0].item()
    fd = central_difference(lambda: float(objective()), bias.data, 0, step=1e-4)
    assert gradient == pytest.approx(fd, rel=0.03)
    assert fd < 0  # a resisting force makes the driver draw more energy: d energy / d bias < 0
    bias.grad = None
    objective(event_gradients=False).backward()
    assert bias.grad[0].item() > 0  # the open-loop path alone says the opposite
    model.close()


def test_held_sample_across_relay_switches(vldm_fmu):
    """The driver's error, held from one controller tick to the next, keeps its gradient through the
    relay's state events between two ticks (its memory shows only there, never at the ticks that
    resample it). 15 s with two relay switches: ANN weights against central differences."""
    model = NeuralFMU(vldm_fmu, TopologyConfig(channels=["der(speed)"], inputs=["speed"], hidden=[4],
                                               kind="residual"), start_values={"cycle": 1})
    with torch.no_grad():
        reference = simulate(model, 65.0, 0.01, record=["speed"], capture=[5000])
    start, target = reference.captured[5000][0], reference.signal("speed")[5000:, 0].clone()
    torch.manual_seed(0)
    with torch.no_grad():
        model.topology.pre_scale.fill_(0.1)
        for p in model.topology.ann.parameters():
            p.copy_(0.3 * torch.randn_like(p))

    def objective():
        run = simulate(model, 15.0, 0.01, starts=[start], record=["speed"], solver="rk4")
        objective.stats = run.stats
        return ((run.signal("speed")[:, 0] - target) ** 2).mean()

    objective().backward()
    assert objective.stats["state_events"] >= 2
    for layer, index in [(0, (1, 0)), (2, (0, 3)), (2, (0, 1))]:
        weight = model.topology.ann[layer].weight
        fd = central_difference(lambda: float(objective()), weight.data, index)
        assert weight.grad[index].item() == pytest.approx(fd, rel=1e-4)
    model.close()


class _EveryKnownAtEveryEvent(EventSensitivity):
    """The reference: every known perturbed on its own at every event, none probed or skipped."""

    def columns(self):
        return np.arange(self.n_knowns)

    def unchecked(self):
        return np.zeros(0, dtype=int)


def test_knowns_acting_only_at_some_events_are_not_dropped(vldm_fmu):
    """In the VLDM the driver's integrators change the discrete states only at some events (the
    state events of its relays), not at the first ones: the event linearisation with probing
    equals the one perturbing every known at every event."""
    model = NeuralFMU(vldm_fmu, TopologyConfig(channels=["der(speed)"], inputs=["speed"], hidden=[4],
                                               kind="residual"), start_values={"cycle": 1})
    torch.manual_seed(0)
    with torch.no_grad():
        for p in model.topology.ann.parameters():
            p.copy_(0.01 * torch.randn_like(p))

    def gradient(sensitivity):
        model.zero_grad()
        run = simulate(model, 12.0, 0.01, record=["energy"], sensitivity=sensitivity)
        run.signal("energy").pow(2).mean().backward()
        return model.topology.ann[0].weight.grad.clone(), run.stats

    n_knowns = model.info.n_states
    probed, stats = gradient(EventSensitivity(n_knowns))
    reference, _ = gradient(_EveryKnownAtEveryEvent(n_knowns))
    assert stats["state_events"] > 0
    work = stats["event_sensitivity"]
    assert work["perturbations"] / work["events"] < n_knowns / 2   # the probing saves work
    # the shadows add one event iteration per event (the held driver error, see EventSensitivity)
    assert work["event_iterations_per_event"] < n_knowns / 2 + 1
    torch.testing.assert_close(probed, reference, rtol=1e-12, atol=0.0)
    model.close()


def test_start_from_standstill_between_controller_ticks(vldm_fmu):
    """At rest, an ANN force that pushes the car backwards makes the driver's held error grow; the
    throttle integrator then raises the start margin until the car starts between two controller
    ticks (a state event of the start indicator, which depends on the held error). The event time
    moves with the held error, and the held error's shadow, which has not crossed yet at the
    nominal event time, is measured on the nominal branch. 100-112 s of the cycle with the set-up
    of benchmarks/bench_gradient.py (a loss on speed, power and energy against the plain FMU): the
    gradient along random first-layer weights against central differences (3.8 % off before)."""
    torch.manual_seed(0)   # the ANN's initial weights (its last layer set below)
    model = NeuralFMU(vldm_fmu, TopologyConfig(channels=["der(speed)"], inputs=["speed"], hidden=[16, 16],
                                               kind="residual"), start_values={"cycle": 1})
    record = ["speed", "power", "energy"]
    with torch.no_grad():
        reference = simulate(model, 112.0, 0.01, record=record + ["der(speed)"], capture=[10000])
        start = reference.captured[10000][0]
        target = simulate(model, 12.0, 0.01, starts=[start], record=record).values.detach()
    scale = target.var(dim=0)
    model.topology.initialise_scaling(reference.numpy("speed")[:, :1], reference.numpy("der(speed)")[:, :1])
    with torch.no_grad():   # a correction of about 5 % of der(speed)'s spread
        model.topology.ann[-1].weight.normal_(0.0, 0.05)
        model.topology.ann[-1].bias.normal_(0.0, 0.05)
    weight = model.topology.ann[0].weight
    direction = torch.randn(weight.shape, generator=torch.Generator().manual_seed(1), dtype=weight.dtype)
    direction /= direction.norm()

    def objective():
        run = simulate(model, 12.0, 0.01, starts=[start], record=record, solver="rk4")
        objective.stats = run.stats
        return (((run.values - target) ** 2).mean(dim=0) / scale).mean()

    objective().backward()
    assert objective.stats["state_events"] >= 3   # the ANN's drift starts and stops the car
    slope = float((weight.grad * direction).sum())
    base = weight.detach().clone()
    step = 1e-6 * float(base.norm())
    with torch.no_grad():
        weight.copy_(base + step * direction)
        plus = float(objective())
        weight.copy_(base - step * direction)
        minus = float(objective())
        weight.copy_(base)
    assert slope == pytest.approx((plus - minus) / (2 * step), rel=1e-3)
    model.close()
