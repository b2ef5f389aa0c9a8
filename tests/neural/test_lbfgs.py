"""L-BFGS through the solver (Trainer._lbfgs_step) on the DC drive with an undeclared Coulomb
friction: its line search must recover from a first trial that overshoots or diverges. The
references are simulations without gradient: the loss at the trial points and a finite difference
of the loss along the gradient."""
import math
import warnings

import numpy as np
import pytest
import torch

from fmubuilder.build import example_fmu
from fmubuilder.data import MeasuredData
from fmubuilder.neural.model import NeuralFMU
from fmubuilder.neural.topology import TopologyConfig
from fmubuilder.neural.train import LBFGS_LINE_SEARCH_EVALUATIONS, TrainSettings, Trainer, network_parameters
from fmubuilder.simulation import simulate

CONFIG = TopologyConfig(channels=["der(speed)"], inputs=["speed"], hidden=[8], kind="residual")


@pytest.fixture(scope="module")
def coulomb_data():
    """10 s of the speed-controlled drive with Coulomb friction; its speed measured with noise."""
    truth = simulate(example_fmu("dc_drive_truth_coulomb"), stop_time=10.0, solver="rk4", step_size=0.001,
                     output_interval=0.05, variables=["speed"])
    speed = truth["speed"] + 0.1 * np.random.default_rng(0).standard_normal(truth.time.size)
    return MeasuredData(truth.time, {"speed": speed}, source="dc_drive coulomb")


@pytest.fixture
def trainer(dc_drive_fmu, coulomb_data):
    """The zero-initialised residual ANN, 8 elements, RK4 at 0.01 s (as hybridize trains)."""
    settings = TrainSettings(epochs=2, element_length=1.25, step_size=0.01, solver="rk4", optimizer="lbfgs",
                             progress=False, sensor_lag=0.0)
    torch.manual_seed(0)
    with NeuralFMU(dc_drive_fmu, CONFIG) as model:
        trainer = Trainer(model, coulomb_data, settings, 0.0)
        trainer.prepare()
        yield trainer


def parameters(trainer) -> list[torch.Tensor]:
    """The parameters L-BFGS moves."""
    topology = trainer.model.topology
    return network_parameters(topology, [p for p in topology.parameters() if p.requires_grad])


def loss_and_gradient(trainer) -> tuple[float, torch.Tensor]:
    params = parameters(trainer)
    for p in params:
        p.grad = None
    loss = trainer.batch_loss(trainer.elements, carry=False)
    loss.backward()
    gradient = torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).flatten() for p in params])
    for p in trainer.model.topology.parameters():
        p.grad = None
    return float(loss.detach()), gradient


def loss_at(trainer, step: torch.Tensor) -> float:
    """The loss (no gradient) with the parameters moved by `step`, then put back."""
    params = parameters(trainer)
    saved = [p.detach().clone() for p in params]
    with torch.no_grad():
        offset = 0
        for p in params:
            p.add_(step[offset:offset + p.numel()].view_as(p))
            offset += p.numel()
        loss = float(trainer.batch_loss(trainer.elements, carry=False))
        for p, value in zip(params, saved):
            p.copy_(value)
    return loss


def test_lbfgs_steps_back_from_an_overshooting_first_trial(trainer):
    """The gradient agrees with a finite difference of the loss, and torch's first trial (step
    1/|g|_1 along -g) raises the loss; the step must shorten it and lower the loss instead of
    staying put (with torch's default max_eval of 1 the line search had no evaluation left)."""
    start, gradient = loss_and_gradient(trainer)
    epsilon = 1e-4 / float(gradient.norm())
    slope = (loss_at(trainer, -epsilon * gradient) - start) / epsilon
    assert slope == pytest.approx(-float(gradient @ gradient), rel=0.05)
    first_trial = -gradient / float(gradient.abs().sum())
    assert loss_at(trainer, first_trial) > start
    trainer.fit()
    losses = [h["loss"] for h in trainer.history]
    assert losses[0] == pytest.approx(start, rel=1e-12)
    assert losses[1] < start - 1e-3


def test_lbfgs_does_not_accept_a_diverged_trial(trainer):
    """A first trial so long that the simulation diverges (states overflow, the loss is not a
    number): the line search brackets it and returns to finite parameters with a lower loss,
    and the finite-difference Jacobians at the diverged states stay silent."""
    start, gradient = loss_and_gradient(trainer)
    params = parameters(trainer)
    optimizer = trainer._optimizer(params, lbfgs=True)
    optimizer.param_groups[0]["lr"] = 32.0
    first_trial = -32.0 * gradient / float(gradient.abs().sum())
    assert not math.isfinite(loss_at(trainer, first_trial))
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        assert trainer._lbfgs_step(optimizer, None, 0) == [pytest.approx(start, rel=1e-12)]
    assert all(bool(torch.isfinite(p).all()) for p in params)
    after = loss_at(trainer, torch.zeros_like(gradient))
    assert after < start
    assert trainer.loss_evaluations <= 1 + LBFGS_LINE_SEARCH_EVALUATIONS   # the start and the line search
