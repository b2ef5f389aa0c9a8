"""The training's loss gradient from the compiled core's forward sensitivities (neural/core_gradient.py)
against independent references: central differences of the same loss evaluated without gradient,
and the torch batch solver's gradient of the training's loss. The DC drive (time events of its
set-point profile, no discrete variables) and the Reference FMU VanDerPol."""
import numpy as np
import pytest
import torch

from fmubuilder.build import example_fmu
from fmubuilder.data import MeasuredData
from fmubuilder.neural import core_gradient
from fmubuilder.neural.model import NeuralFMU
from fmubuilder.neural.solve import ElementStart, simulate
from fmubuilder.neural.topology import TopologyConfig
from fmubuilder.neural.train import TrainSettings, Trainer
from fmubuilder.simulation import simulate as simulate_engine
from tests.reference_fmus import reference_fmu

SIGNALS = ("speed", "current", "power", "temperature")


@pytest.fixture(scope="module")
def windage_truth():
    return simulate_engine(example_fmu("dc_drive_truth_windage"), stop_time=6.1, solver="rk4", step_size=0.001,
                           output_interval=0.001, variables=list(SIGNALS))


def windage_data(truth, offset: float = 0.0):
    """6 s of the speed-controlled drive with windage (two set-point steps) from `offset`, four
    signals every 50 ms with noise."""
    times = offset + 0.05 * np.arange(121)
    rng = np.random.default_rng(0)
    signals = {name: np.interp(times, truth.time, truth[name]) + 0.01 * np.std(truth[name]) *
               rng.standard_normal(times.size) for name in SIGNALS}
    return MeasuredData(times, signals, source="dc_drive windage")


def make_trainer(fmu, data, aliases=None, sensor_lag=0.1):
    """Two elements of 3 s, RK4 at 0.01 s; the ANN (8 x 8 tanh, gates) away from its neutral start."""
    settings = TrainSettings(element_length=3.0, step_size=0.01, solver="rk4", optimizer="lbfgs", progress=False,
                             sensor_lag=sensor_lag, aliases=aliases or {})
    torch.manual_seed(0)
    model = NeuralFMU(fmu, TopologyConfig(channels=["der(speed)"], inputs=["speed", "current"], hidden=[8, 8],
                                          kind="gates"))
    trainer = Trainer(model, data, settings, 0.0)
    trainer.prepare()
    with torch.no_grad():
        model.topology.gate_ann.fill_(0.3)
        for parameter in model.topology.ann.parameters():
            parameter.add_(0.05 * torch.randn_like(parameter))
    return trainer


def trained(model):
    return [p for p in model.topology.parameters() if p.requires_grad]


def gradient_of(loss_function, model):
    """(loss, flat gradient) of loss_function() by backward."""
    for p in model.topology.parameters():
        p.grad = None
    loss = loss_function()
    loss.backward()
    flat = torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).flatten() for p in trained(model)])
    return float(loss.detach()), flat


def central_differences(loss_function, model, indices, step=1e-6):
    """d loss / d parameter by central differences of loss_function() without gradient."""
    where = [(p, i) for p in trained(model) for i in range(p.numel())]
    values = []
    for index in indices:
        parameter, i = where[index]
        base = float(parameter.data.view(-1)[i])
        delta = step * max(1.0, abs(base))
        losses = []
        for value in (base + delta, base - delta):
            parameter.data.view(-1)[i] = value
            with torch.no_grad():
                losses.append(float(loss_function()))
        parameter.data.view(-1)[i] = base
        values.append((losses[0] - losses[1]) / (2 * delta))
    return np.array(values)


def core_loss(trainer):
    """The training's loss of all elements with the core's run (gradient or not)."""
    def loss():
        with torch.enable_grad():
            trajectory = core_gradient.CoreElements(trainer.model, trainer.element_duration, trainer.step,
                                                    [e.start for e in trainer.elements], trainer.recorded,
                                                    trainer.settings.solver, trainer.inputs).trajectory(False)
        assert trajectory is not None
        residuals = trainer._residuals(trajectory, trainer.elements)
        terms = [(residuals[name] ** 2).mean() / trainer.scale[name] for name in trainer.loss_signals]
        value = sum(terms) / len(terms)
        return value if torch.is_grad_enabled() else value.detach()
    return loss


@pytest.mark.parametrize("aliases, offset", [({}, 0.0), ({"power": "der(energy)"}, 0.0), ({}, 0.004)],
                         ids=["power read", "power as der(energy)", "events between grid points"])
def test_dc_drive_loss_gradient_against_differences_and_the_torch_solver(dc_drive_fmu, windage_truth, aliases, offset):
    """A state, an FMU variable (power, by differences of its reading) or a corrected derivative,
    through the sensor's lag; the drive's set-point profile has time events inside the elements, on
    grid points, or with the data from 4 ms on between them."""
    trainer = make_trainer(dc_drive_fmu, windage_data(windage_truth, offset), aliases)
    model = trainer.model
    assert core_gradient.exact_in_core(model)
    trajectory = core_gradient.simulate_for_loss(model, trainer.element_duration, trainer.step,
                                                 starts=[e.start for e in trainer.elements], record=trainer.recorded,
                                                 solver="rk4", inputs=trainer.inputs)
    assert trajectory.stats.get("core_gradient")
    assert bool(trajectory.inner) == bool(offset)
    with torch.no_grad():
        reference = simulate(model, trainer.element_duration, trainer.step, starts=[e.start for e in trainer.elements],
                             record=trainer.recorded, solver="rk4", inputs=trainer.inputs)
    np.testing.assert_allclose(trajectory.values.detach().numpy(), reference.values.numpy(), rtol=1e-9, atol=1e-9)

    loss, gradient = gradient_of(core_loss(trainer), model)
    largest = np.argsort(-np.abs(gradient.numpy()))[:4]
    differences = central_differences(core_loss(trainer), model, largest)
    np.testing.assert_allclose(gradient.numpy()[largest], differences, rtol=1e-5)

    # the training's loss (Trainer.batch_loss) takes the core's path, and agrees with the torch solver's
    assert trainer.batch_loss(trainer.elements, carry=False).grad_fn is not None
    _, training = gradient_of(lambda: trainer.batch_loss(trainer.elements, carry=False), model)
    np.testing.assert_allclose(training.numpy(), gradient.numpy(), rtol=1e-12, atol=1e-12)
    torch_loss, torch_gradient = gradient_of(lambda: torch_solver_loss(trainer), model)
    # the two read a derivative or an output at the end of a step differently (the core: at the
    # step's end; the torch solver: at RK4's last stage), so they agree closely, not exactly
    assert loss == pytest.approx(torch_loss, rel=1e-3)
    cosine = float(gradient @ torch_gradient / (gradient.norm() * torch_gradient.norm()))
    assert cosine > 1 - 1e-6
    np.testing.assert_allclose(gradient.numpy()[largest], torch_gradient.numpy()[largest], rtol=1e-3)
    model.close()


def torch_solver_loss(trainer):
    trajectory = simulate(trainer.model, trainer.element_duration, trainer.step,
                          starts=[e.start for e in trainer.elements], record=trainer.recorded, solver="rk4",
                          inputs=trainer.inputs)
    residuals = trainer._residuals(trajectory, trainer.elements)
    terms = [(residuals[name] ** 2).mean() / trainer.scale[name] for name in trainer.loss_signals]
    return sum(terms) / len(terms)


VAN_DER_POL = {
    "one channel": TopologyConfig(channels=["der(x1)"], inputs=["x0", "x1"], hidden=[6], kind="residual"),
    "two channels, sigmoid, reading a derivative": TopologyConfig(
        channels=["der(x0)", "der(x1)"], inputs=["x1", "der(x0)"], hidden=[5, 4], activation="sigmoid",
        kind="gates"),
    "a base term": TopologyConfig(channels=["der(x1)"], inputs=["x0", "x1"], hidden=[4], kind="residual",
                                  base_terms=[{"variable": "x0", "basis": "w*|w|", "center": 0.2, "coefficient": -0.3},
                                              {"variable": "x1", "basis": "|w|", "center": 0.0, "coefficient": 0.1},
                                              {"variable": "x0", "basis": "1", "center": 0.0, "coefficient": 0.05}]),
}


@pytest.mark.parametrize("topology", VAN_DER_POL)
@pytest.mark.parametrize("solver, step", [("rk4", 0.05), ("euler", 0.01)])
def test_van_der_pol_weighted_records(solver, step, topology):
    """The Reference FMU VanDerPol with an ANN on its derivatives: a weighted sum of a state and a
    corrected derivative over two elements from saved FMU states."""
    torch.manual_seed(3)
    model = NeuralFMU(reference_fmu("VanDerPol"), TopologyConfig.from_dict(VAN_DER_POL[topology].to_dict()))
    with torch.no_grad():
        model.topology.ann[-1].weight.normal_(0.0, 0.3)
        model.topology.ann[-1].bias.fill_(0.1)
        model.topology.gate_ann.fill_(0.5)
        run = simulate(model, 2.0, step, record=["x0"], solver=solver, capture=[0, round(1.0 / step)])
    starts = [run.captured[0][0], run.captured[round(1.0 / step)][0]]
    assert core_gradient.exact_in_core(model)
    weights = torch.from_numpy(np.random.default_rng(1).standard_normal((round(1.5 / step) + 1, 2, 2)))

    def objective():
        with torch.enable_grad():
            trajectory = core_gradient.simulate_for_loss(model, 1.5, step, starts=starts, record=["x0", "der(x1)"],
                                                         solver=solver)
        assert trajectory.stats.get("core_gradient")
        value = (weights * trajectory.values).sum() + (trajectory.values ** 2).sum()
        return value if torch.is_grad_enabled() else value.detach()

    def torch_objective():
        trajectory = simulate(model, 1.5, step, starts=starts, record=["x0", "der(x1)"], solver=solver)
        return (weights * trajectory.values).sum() + (trajectory.values ** 2).sum()

    _, gradient = gradient_of(objective, model)
    every = np.arange(gradient.numel())
    np.testing.assert_allclose(gradient.numpy(), central_differences(objective, model, every), rtol=1e-5, atol=1e-7)
    _, torch_gradient = gradient_of(torch_objective, model)
    # the Jacobians by forward differences: agreement to their accuracy
    np.testing.assert_allclose(gradient.numpy(), torch_gradient.numpy(), rtol=1e-6, atol=1e-9)
    model.close()


@pytest.mark.parametrize("example", ["vldm", "sampled_plant", "bouncing_ball"])
def test_models_with_discrete_states_or_state_events_keep_the_torch_solver(example):
    """The VLDM's sampled driver, a sampled PI controller, a bouncing ball's state events: the
    modelDescription says the core's gradient would miss a path, so the loss runs in torch."""
    fmu = example_fmu(example)
    from fmubuilder.fmi import read_model_info
    info = read_model_info(fmu)
    model = NeuralFMU(fmu, TopologyConfig(channels=[info.derivatives[-1].name], inputs=[info.states[-1].name],
                                          hidden=[4]))
    assert model.topology.has_ann
    assert not core_gradient.exact_in_core(model)
    model.close()


def test_a_start_without_saved_state_keeps_the_torch_solver(dc_drive_fmu):
    model = NeuralFMU(dc_drive_fmu, TopologyConfig(channels=["der(speed)"], inputs=["speed"], hidden=[4]))
    trajectory = core_gradient.simulate_for_loss(model, 0.5, 0.01, starts=[ElementStart(0.0)], record=["speed"],
                                                 solver="rk4")
    assert not trajectory.stats.get("core_gradient")
    model.close()
