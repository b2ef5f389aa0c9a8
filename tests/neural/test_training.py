"""Training runs on cheap models whose data come from the same C model with a changed parameter
(or a compiled-in extra effect), so the undeclared effect is known and the error must fall."""
import json

import numpy as np
import pytest

from fmubuilder.errors import FmuBuilderError
from fmubuilder.data import MeasuredData
from fmubuilder.neural.train import train_neural_fmu
from fmubuilder.simulation import simulate as engine_simulate

from .conftest import plant_data


def factor(metrics, key, signal):
    return metrics[key]["before"][signal]["mse"] / metrics[key]["after"][signal]["mse"]


def test_collocation_and_fine_tuning_without_directional_derivatives(plant_fmu):
    """sampled_plant (no directional derivatives, sampled PI with a discrete integrator) with three
    times its declared friction; the held-out data use another set-point profile."""
    train, _ = plant_data(plant_fmu, [0, 1, 1.001, 2.5, 2.501, 4], [1, 1, 2, 2, 0.5, 0.5], 4.0, seed=0)
    test, _ = plant_data(plant_fmu, [0, 1.5, 1.501, 3], [1.5, 1.5, 0.7, 0.7], 3.0, seed=1)
    result = train_neural_fmu(plant_fmu, train, targets=["der(w)"], inputs=["w", "der(w)"], topology="residual",
                              hidden=[8], epochs=2, element_length=1.0, batch_size=2, step_size=0.002,
                              learning_rate=1e-3, ccpt_iterations=800, ccpt_window=0.1, progress=False, test_data=test)
    assert factor(result.metrics, "errors", "w") > 50
    assert factor(result.metrics, "test_errors", "w") > 50
    result.model.close()


def test_training_across_state_events_with_directional_derivatives(ball_fmu):
    """The bouncing ball falls with g = 8 instead of 9.81: the gates learn der(v) from the impacts
    in the data (ODE-solver training only); held out: dropped from another height."""
    def drop(h0, seed):
        run = engine_simulate(ball_fmu, stop_time=1.4, start_values={"g": 8.0, "h": h0}, solver="rk4",
                              step_size=0.001, output_interval=0.01, variables=["h"])
        noise = 0.001 * np.random.default_rng(seed).standard_normal(run.time.size)
        return MeasuredData(run.time, {"h": run["h"] + noise}, source="ball")

    result = train_neural_fmu(ball_fmu, drop(1.0, 0), targets=["der(v)"], inputs=["v", "der(v)"], topology="gates",
                              hidden=[4], epochs=22, step_size=0.005, solver="rk4", learning_rate=1e-2, decay=0.97,
                              element_length=10.0, progress=False, test_data=drop(1.3, 1))
    assert factor(result.metrics, "errors", "h") > 10
    assert factor(result.metrics, "test_errors", "h") > 10
    result.model.close()


def test_training_on_an_output_signal(dc_drive_fmu):
    """dc_drive with undeclared windage, only its electrical power (an output) measured."""
    from fmubuilder.build import example_fmu
    truth = engine_simulate(example_fmu("dc_drive_truth_windage"), stop_time=10.0, solver="rk4", step_size=0.0005,
                            output_interval=0.01, variables=["power"])
    noise = 0.5 * np.random.default_rng(0).standard_normal(truth.time.size)
    data = MeasuredData(truth.time, {"power": truth["power"] + noise}, source="dc_drive")
    result = train_neural_fmu(dc_drive_fmu, data, targets=["der(speed)"], inputs=["speed"], topology="residual",
                              hidden=[8], epochs=6, element_length=2.0, step_size=0.002, learning_rate=1e-2,
                              progress=False)
    assert factor(result.metrics, "errors", "power") > 4
    result.model.close()


def test_seed_budget_checkpoint_and_resume(plant_fmu, tmp_path):
    train, _ = plant_data(plant_fmu, [0, 1, 1.001, 2], [1, 1, 2, 2], 2.0, seed=0)
    common = dict(targets=["der(w)"], inputs=["w", "der(w)"], hidden=[4], element_length=0.5, step_size=0.004,
                  nipt_iterations=50, progress=False)
    first = train_neural_fmu(plant_fmu, train, epochs=2, seed=7, **common)
    second = train_neural_fmu(plant_fmu, train, epochs=2, seed=7, **common)
    assert [h["loss"] for h in first.history] == [h["loss"] for h in second.history]
    assert first.metrics["epochs"] == first.metrics["epochs_planned"] == 2
    assert not first.metrics["cut_short_by_time_budget"]
    first.model.close(), second.model.close()

    output = tmp_path / "plant.nfmu"
    budget = train_neural_fmu(plant_fmu, train, epochs=1000, time_budget=3.0, output=output,
                              metrics_path=tmp_path / "m.json", **common)
    assert 0 < budget.metrics["epochs"] < 1000 and budget.metrics["cut_short_by_time_budget"]
    assert output.is_file() and (tmp_path / "plant.nfmu.ckpt").is_file()
    done = budget.metrics["epochs"]
    budget.model.close()
    resumed = train_neural_fmu(plant_fmu, train, epochs=done + 1, output=output, force=True, resume=True, **common)
    assert resumed.metrics["epochs"] == done + 1 and len(resumed.history) == done + 1
    resumed.model.close()
    metrics = json.loads((tmp_path / "m.json").read_text())
    assert set(metrics["errors"]["before"]["w"]) == {"mse", "max_abs", "final"}


def test_bad_input_is_a_one_line_error(plant_fmu, tmp_path):
    train, _ = plant_data(plant_fmu, [0, 1], [1, 1], 1.0, seed=0)
    with pytest.raises(FmuBuilderError, match="not a state derivative"):
        train_neural_fmu(plant_fmu, train, targets=["w"], inputs=["w"], progress=False)
    with pytest.raises(FmuBuilderError, match="unknown variable 'x'"):
        train_neural_fmu(plant_fmu, train, targets=["der(w)"], inputs=["x"], progress=False)
    existing = tmp_path / "out.nfmu"
    existing.write_text("")
    with pytest.raises(FmuBuilderError, match="--force"):
        train_neural_fmu(plant_fmu, train, targets=["der(w)"], inputs=["w"], output=existing, progress=False)


def test_sequential_elements_with_carry_over(plant_fmu):
    """Elements one at a time in time order, each continuing the FMU state just computed."""
    train, _ = plant_data(plant_fmu, [0, 1, 1.001, 2.5, 2.501, 4], [1, 1, 2, 2, 0.5, 0.5], 4.0, seed=0)
    result = train_neural_fmu(plant_fmu, train, targets=["der(w)"], inputs=["w", "der(w)"], hidden=[8],
                              epochs=6, element_length=1.0, order="sequential", step_size=0.004,
                              learning_rate=2e-2, progress=False)
    assert len(result.history) == 6
    assert factor(result.metrics, "errors", "w") > 2
    result.model.close()


def test_losses_are_relative_to_the_plain_fmu(plant_fmu):
    """With loss_scale="reference" every signal's MSE is divided by the plain FMU's on the same
    elements, so the first epoch of a residual hybrid (which starts as the plain FMU) has loss 1."""
    train, _ = plant_data(plant_fmu, [0, 1, 1.001, 2], [1, 1, 2, 2], 2.0, seed=0)
    result = train_neural_fmu(plant_fmu, train, targets=["der(w)"], inputs=["w"], hidden=[4], epochs=1,
                              element_length=0.5, step_size=0.004, progress=False)
    assert result.history[0]["loss"] == pytest.approx(1.0, rel=1e-9)
    result.model.close()


def test_an_overshooting_step_size_is_rewound(plant_fmu):
    """A step size far too large for the problem: with backtracking and keep_best the trained hybrid
    is no worse than the plain FMU on its training data; without them it is."""
    train, _ = plant_data(plant_fmu, [0, 1, 1.001, 2], [1, 1, 2, 2], 2.0, seed=0)
    common = dict(targets=["der(w)"], inputs=["w"], hidden=[8], epochs=8, element_length=0.5, step_size=0.004,
                  learning_rate=1.0, decay=1.0, processing_step_factor=1.0, progress=False)
    guarded = train_neural_fmu(plant_fmu, train, **common)
    reckless = train_neural_fmu(plant_fmu, train, backtrack=False, keep_best=False, **common)
    assert any(h["backtracked"] for h in guarded.history)
    before = guarded.metrics["errors"]["before"]["w"]["mse"]
    assert guarded.metrics["errors"]["after"]["w"]["mse"] <= before
    assert reckless.metrics["errors"]["after"]["w"]["mse"] > 2 * before
    guarded.model.close(), reckless.model.close()


def test_lbfgs_through_the_solver(plant_fmu):
    """L-BFGS over all elements at once: each epoch is one step whose line search evaluates the
    loss on fixed element starts; the loss falls and the held-out error with it."""
    train, _ = plant_data(plant_fmu, [0, 1, 1.001, 2.5, 2.501, 4], [1, 1, 2, 2, 0.5, 0.5], 4.0, seed=0)
    test, _ = plant_data(plant_fmu, [0, 1.5, 1.501, 3], [1.5, 1.5, 0.7, 0.7], 3.0, seed=1)
    result = train_neural_fmu(plant_fmu, train, targets=["der(w)"], inputs=["w"], topology="residual", hidden=[8],
                              epochs=4, element_length=1.0, step_size=0.002, optimizer="lbfgs", progress=False,
                              test_data=test)
    losses = [h["loss"] for h in result.history]
    assert losses[0] == pytest.approx(1.0) and losses == sorted(losses, reverse=True) and losses[-1] < 0.6
    assert result.metrics["loss_evaluations"] >= len(losses)
    assert factor(result.metrics, "test_errors", "w") > 1.5
    result.model.close()
