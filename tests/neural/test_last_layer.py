"""The last layer's refinement through the simulation (neural/last_layer.py): on data made by a
hybrid whose last layer is known, it finds that layer again from a wrong one."""
import sys

import numpy as np
import pytest
import torch

from fmubuilder.data import MeasuredData
from fmubuilder.neural.last_layer import _Problem, refine_last_layer
from fmubuilder.neural.model import NeuralFMU
from fmubuilder.neural.topology import TopologyConfig
from fmubuilder.neural.train import Trainer, TrainSettings, Validation, simulate_over

from .conftest import plant_data

STEP = 0.002


def _trainer(plant_fmu, data: MeasuredData, simulations: int = 0, element_length: float = 10.0,
             validation: MeasuredData | None = None) -> Trainer:
    settings = TrainSettings(element_length=element_length, step_size=STEP, solver="rk4", progress=False, sensor_lag=0.0,
                             last_layer_simulations=simulations)
    config = TopologyConfig(channels=["der(w)"], inputs=["w"], hidden=[6], kind="residual")
    torch.manual_seed(1)
    held_out = None if validation is None else Validation(validation, (validation.start, validation.stop))
    trainer = Trainer(NeuralFMU(plant_fmu, config), data, settings, 0.0, held_out)
    trainer.prepare()
    return trainer


@pytest.fixture(scope="module")
def truth(plant_fmu):
    """(data simulated by a hybrid with a known last layer, its hidden layers and scaling, that layer)."""
    data, _ = plant_data(plant_fmu, [0, 1, 1.001, 2.5, 2.501, 4], [1, 1, 2, 2, 0.5, 0.5], 4.0, seed=0,
                         friction=0.05)
    trainer = _trainer(plant_fmu, data)
    with trainer.model as model:
        last = model.topology.ann[-1]
        with torch.no_grad():
            last.weight.copy_(torch.linspace(-0.4, 0.5, last.weight.numel(), dtype=torch.float64).reshape(last.weight.shape))
            last.bias.fill_(-0.3)
        return _made_by(model, data), model.topology.state_dict()


def _made_by(model: NeuralFMU, data: MeasuredData) -> MeasuredData:
    """The speed the hybrid `model` simulates with the inputs of `data`."""
    result = simulate_over(model, data, STEP, "rk4")
    return MeasuredData(data.time, {"w": np.interp(data.time, result.time, result["w"])}, {},
                        data.inputs, "made by a known hybrid")


def _halved(state: dict) -> dict:
    """The known hybrid with its last layer halved."""
    return {k: (v * 0.5 if k.startswith("ann.2.") else v) for k, v in state.items()}


@pytest.mark.parametrize("element_length", [10.0, 1.0])
def test_the_refinement_finds_a_known_last_layer_again(plant_fmu, truth, element_length):
    """Trained as one element or as four: the refinement simulates the whole run either way."""
    data, state = truth
    trainer = _trainer(plant_fmu, data, simulations=40, element_length=element_length)
    with trainer.model as model:
        wrong = _halved(state)
        model.topology.load_state_dict(wrong)
        before = trainer.engine_differences()["w"]
        done = refine_last_layer(trainer, 40)
        after = trainer.engine_differences()["w"]
        # 6 weights and a bias, searched along the directions their units span over the run
        assert done["kept"] and done["simulations"] <= 40 and done["entries"] == 7 and 1 <= done["unknowns"] <= 7
        assert done["loss_after"] < 1e-6 * done["loss_before"]
        # the data are the truth's simulation: its error falls by three orders of magnitude, and the
        # correction along the measured speeds is the truth's (the layer's entries themselves are
        # not all determined by these data: the hidden units' outputs are nearly collinear)
        assert np.sqrt(np.mean(after ** 2)) < 1e-3 * np.sqrt(np.mean(before ** 2))
        speeds = torch.linspace(float(data.signals["w"].min()), float(data.signals["w"].max()), 50,
                                dtype=torch.float64)[:, None]
        found = model.topology.correction(speeds).detach()
        model.topology.load_state_dict(state)
        expected = model.topology.correction(speeds).detach()
        assert float((found - expected).abs().max()) < 1e-3 * float(expected.abs().max())

def test_a_budget_below_one_step_leaves_the_layer(plant_fmu, truth):
    data, state = truth
    trainer = _trainer(plant_fmu, data)
    with trainer.model as model:
        before = model.topology.ann[-1].weight.detach().clone()
        unknowns = _Problem(trainer, model.topology).start().size
        # a step costs the start, a column per unknown and a trial
        assert refine_last_layer(trainer, unknowns + 1) is None
        torch.testing.assert_close(model.topology.ann[-1].weight, before, atol=0, rtol=0)


def test_each_unknown_moves_the_output_by_one_along_the_run_and_no_two_alike(plant_fmu, truth):
    """The search's unknowns, seen through the hybrid's own correction along the reference run:
    a unit move of one shifts the ANN's output by a root mean square of 1, and two moves' shifts
    are orthogonal."""
    data, state = truth
    trainer = _trainer(plant_fmu, data)
    with trainer.model as model:
        topology = model.topology
        topology.load_state_dict(state)
        problem = _Problem(trainer, topology)
        inputs = torch.from_numpy(trainer.reference_samples()[0])
        with torch.no_grad():
            start = topology.correction(inputs)[:, 0] / topology.post_scale[0]
            shifts = []
            for k in range(problem.start().size):
                move = np.zeros(problem.start().size)
                move[k] = 1.0
                problem.set(move)
                shifts.append((topology.correction(inputs)[:, 0] / topology.post_scale[0] - start).numpy())
        shifts = np.stack(shifts, axis=1)
        gram = shifts.T @ shifts / shifts.shape[0]
        np.testing.assert_allclose(gram, np.eye(len(gram)), atol=1e-6)
        assert 1 <= len(gram) < 7       # the 6 tanh units of one input are nearly dependent


def test_the_search_ends_when_converged_where_the_whole_budget_finds_no_lower_loss(plant_fmu, truth, monkeypatch):
    """On noisy data the best layer leaves the noise: once there, the Gauss-Newton step promises
    nothing and the search ends, at the loss of the known layer and of the same search with its
    whole budget."""
    from fmubuilder.neural import last_layer
    data, state = truth
    noise = np.random.default_rng(3).normal(0.0, 0.01, data.time.size)
    noisy = MeasuredData(data.time, {"w": data.signals["w"] + noise}, {}, data.inputs, "the known hybrid, noisy")
    budget, default = 60, last_layer.CONVERGED_BELOW
    results = {}
    for converged_below in (default, 0.0):
        monkeypatch.setattr(last_layer, "CONVERGED_BELOW", converged_below)
        trainer = _trainer(plant_fmu, noisy)
        with trainer.model as model:
            model.topology.load_state_dict(_halved(state))
            results[converged_below] = refine_last_layer(trainer, budget)
            model.topology.load_state_dict(state)
            known = float(np.mean(trainer.engine_differences()["w"] ** 2)) / trainer.scale["w"]
    stopped, whole = results[default], results[0.0]
    assert stopped["ended"] == "converged" and stopped["simulations"] < budget / 2
    assert whole["ended"] == "the budget is spent"
    assert stopped["loss_after"] < 0.5 * stopped["loss_before"]
    assert stopped["loss_after"] <= 1.001 * known
    assert stopped["loss_after"] == pytest.approx(whole["loss_after"], rel=1e-4)


@pytest.mark.parametrize("terminal", [False, True])
def test_the_refinements_bar_shows_on_a_terminal_only(plant_fmu, truth, monkeypatch, capsys, terminal):
    """A training that shows progress draws the refinement's bar as every other bar: only where
    stderr is a terminal (a log file or a pipe gets no bar drawings)."""
    data, state = truth
    trainer = _trainer(plant_fmu, data)
    trainer.settings.progress = True
    monkeypatch.setattr(sys.stderr, "isatty", lambda: terminal)
    with trainer.model as model:
        model.topology.load_state_dict(_halved(state))
        capsys.readouterr()
        assert refine_last_layer(trainer, 10) is not None
    drawn = "refining the ANN's last layer" in capsys.readouterr().err
    assert drawn == terminal


@pytest.mark.parametrize("validation_by", ["the known layer", "the halved layer"])
def test_every_step_kept_is_scored_on_the_validation_data_and_the_best_kept(plant_fmu, truth, validation_by):
    """Trained on the known layer's data from the halved layer. Validation data made by the known
    layer: every step the search keeps scores lower there (the same data: the score is the training
    loss over the plain model's), and the trainer keeps the last. Made by the halved layer, every
    step scores higher than its start, which the trainer keeps."""
    data, state = truth
    with NeuralFMU(plant_fmu, TopologyConfig(channels=["der(w)"], inputs=["w"], hidden=[6], kind="residual")) as maker:
        maker.topology.load_state_dict(state if validation_by == "the known layer" else _halved(state))
        validation = _made_by(maker, data)
    trainer = _trainer(plant_fmu, data, validation=validation)
    with trainer.model as model:
        model.topology.load_state_dict(_halved(state))
        at_start = trainer.track_validation(0, "the halved layer")
        done = refine_last_layer(trainer, 20, stage=(1, "search"))
        at_end = trainer.validation_score()       # simulated afresh, not the search's record
        scores = done["validation_scores"]
        assert done["kept"] and len(scores) >= 2
        if validation_by == "the known layer":
            assert all(later < earlier for earlier, later in zip([at_start, *scores], scores))
            assert done["best_validation"] == pytest.approx(at_end, rel=1e-9)
            assert trainer.validation_best[3] == "search"
        else:
            assert min(scores) > at_start
            assert trainer.validation_best[3] == "the halved layer"
            trainer.restore_best()
            torch.testing.assert_close(model.topology.ann[-1].weight, 0.5 * state["ann.2.weight"])
