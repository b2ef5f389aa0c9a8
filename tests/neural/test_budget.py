"""The training's work counted in loss evaluations (TrainSettings.budget): every optimizer spends
exactly the budget, counted here by wrapping the loss itself, and L-BFGS set up as hybridize sets
it up lowers the training loss from where the warm start left it."""
from dataclasses import replace
from types import SimpleNamespace

import pytest
import torch

from fmubuilder.errors import FmuBuilderError
from fmubuilder.hybridize import recipe, workflow
from fmubuilder.neural.model import NeuralFMU
from fmubuilder.neural.topology import TopologyConfig
from fmubuilder.neural import warm_start
from fmubuilder.neural.train import Trainer, train_neural_fmu

from .conftest import plant_data

COMMON = dict(targets=["der(w)"], inputs=["w"], topology="residual", hidden=[8], element_length=1.0,
              step_size=0.002, progress=False)


@pytest.fixture(scope="module")
def plant_train(plant_fmu):
    train, _ = plant_data(plant_fmu, [0, 1, 1.001, 2.5, 2.501, 4], [1, 1, 2, 2, 0.5, 0.5], 4.0, seed=0)
    return train


@pytest.fixture
def counted_losses(monkeypatch):
    """The number of times the training loss (a simulation of a batch of elements) is computed."""
    calls = []
    original = Trainer.batch_loss

    def batch_loss(self, batch, carry=True):
        calls.append(len(batch))
        return original(self, batch, carry)

    monkeypatch.setattr(Trainer, "batch_loss", batch_loss)
    return calls


@pytest.mark.parametrize("optimizer", ["adam", "lbfgs"])
def test_the_budget_is_spent_exactly(plant_fmu, plant_train, counted_losses, optimizer):
    """5 loss evaluations whatever the optimizer: Adam's steps, L-BFGS's line searches (the last one
    given what is left)."""
    result = train_neural_fmu(plant_fmu, plant_train, budget=5, optimizer=optimizer, **COMMON)
    result.model.close()
    assert len(counted_losses) == 5 == result.metrics["loss_evaluations"]
    assert len(set(counted_losses)) == 1          # each a pass over all elements (one batch)
    steps = [h["loss_evaluations"] for h in result.history]
    if optimizer == "adam":
        assert steps == [1, 2, 3, 4, 5]
    else:                                        # L-BFGS's steps of several evaluations each
        assert steps[-1] == 5 and len(steps) < 5


def test_epochs_still_count_steps_without_a_budget(plant_fmu, plant_train, counted_losses):
    result = train_neural_fmu(plant_fmu, plant_train, epochs=2, optimizer="lbfgs", **COMMON)
    result.model.close()
    assert result.metrics["epochs"] == 2 and len(counted_losses) == result.metrics["loss_evaluations"] > 2


def test_a_negative_budget_is_refused(plant_fmu, plant_train):
    with pytest.raises(FmuBuilderError, match="budget must be >= 0"):
        train_neural_fmu(plant_fmu, plant_train, budget=-1, **COMMON)


def test_lbfgs_as_hybridize_sets_it_up_lowers_the_training_loss(plant_fmu, plant_train, monkeypatch):
    """The workflow's training settings (collocation warm start's fits, L-BFGS after its Adam steps),
    RK4 as hybridize trains: the loss over all elements, simulated again without gradient on the
    same element starts, is lower after 6 loss evaluations than after the warm start."""
    monkeypatch.setattr(recipe, "OPTIMIZER", "lbfgs")
    # the warm start's fits alone: its last layer through the simulation would leave the training
    # little to do on this plant (the loss it reaches is within 2 % of the trained one)
    monkeypatch.setattr(warm_start, "_through_simulation", lambda trainer, loss, trials=None: None)
    diagnosis = SimpleNamespace(errors=[SimpleNamespace(signal="w", significant=True)])
    settings = workflow._training_settings(plant_train, diagnosis, budget=6)
    assert settings.optimizer == "lbfgs" and settings.warm_start
    # the training alone: no refinement of the last layer after it
    settings = replace(settings, element_length=1.0, last_layer_simulations=0, budget=6, solver="rk4", step_size=0.002,
                       progress=False, sensor_lag=0.0)
    config = TopologyConfig(channels=["der(w)"], inputs=["w"], hidden=[8], kind="residual")
    torch.manual_seed(0)
    with NeuralFMU(plant_fmu, config) as model:
        trainer = Trainer(model, plant_train, settings, 0.0)
        trainer.prepare()
        with torch.no_grad():
            start = float(trainer.batch_loss(trainer.elements, carry=False))
        lbfgs_starts = [e.start for e in trainer.elements]
        trainer.fit()
        assert trainer.loss_evaluations == 6
        assert [e.start for e in trainer.elements] == lbfgs_starts     # L-BFGS keeps the element starts fixed
        with torch.no_grad():
            end = float(trainer.batch_loss(trainer.elements, carry=False))
    assert end < 0.9 * start
