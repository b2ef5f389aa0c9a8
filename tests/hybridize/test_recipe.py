"""One source for the NeuralFMU training's settings: `fmubuilder train` defaults to TrainSettings'
defaults, and `fmubuilder train --recipe hybridize` trains the network `hybridize` trains."""
import time
from dataclasses import replace
from types import SimpleNamespace

import pytest
import torch

from fmubuilder import cli, synth
from fmubuilder.build import example_fmu
from fmubuilder.cli.train import _training
from fmubuilder.fmi import read_model_info
from fmubuilder.hybridize import recipe, workflow
from fmubuilder.hybridize.evaluate import Scoring
from fmubuilder.neural.io import load_neural_fmu
from fmubuilder.neural.settings import TrainSettings

CHANNEL, INPUTS, LOSS = "der(speed)", ["speed"], ["speed", "current"]
BENCH = dict(signals=("speed", "current", "power", "temperature"),
             noise_std={"speed": 0.1, "current": 0.02, "power": 1.0, "temperature": 0.02})


def _train_parser():
    parser = cli.build_parser()
    commands = next(a for a in parser._actions if a.dest == "command")
    return commands.choices["train"]


def test_every_training_option_defaults_to_its_train_settings_field():
    fields = TrainSettings.__dataclass_fields__
    options = [a for a in _train_parser()._actions if a.dest in fields]
    assert len(options) > 10
    for action in options:
        assert action.default == fields[action.dest].default, action.option_strings


def test_train_without_options_trains_with_the_default_settings():
    args = cli.parse(["train", "m.fmu", "--data", "d.csv", "--target", CHANNEL, "--inputs", "speed", "-o", "t"])
    _, _, settings, validation = _training(args)
    assert settings == replace(TrainSettings(), progress=True) and validation is None


@pytest.fixture(scope="module")
def windage(tmp_path_factory):
    settings = synth.BenchSettings(seed=0, **BENCH)
    measurement = synth.measure(example_fmu("dc_drive_truth_windage"), start_time=0.0, stop_time=6.0,
                                settings=settings)
    return synth.write_measurement(measurement, tmp_path_factory.mktemp("recipe") / "train.csv")


def _trained_by_the_workflow(fmu, csv, folder):
    """The NeuralFMU's training as hybridize calls it, on `csv` as the only training run."""
    info = read_model_info(fmu)
    roles = workflow._assign_roles(info, csv, None, None, None, csv, None)
    first = roles.train[0]
    diagnosis = SimpleNamespace(errors=[SimpleNamespace(signal=s, significant=s in LOSS) for s in first.data.names])
    ctx = workflow._Context(fmu, info, roles, Scoring.checked(fmu, first.samples(), first.start_values), folder,
                            lambda *a: None, 1, 0, None, time.perf_counter(), workflow.Scores(fmu), progress=False)
    settings = workflow._training_settings(first.samples(), diagnosis, ctx.budget)
    return workflow._train_neural(ctx, [CHANNEL], INPUTS, {}, settings, "neural")


def test_train_with_the_hybridize_recipe_trains_the_network_hybridize_trains(windage, tmp_path, monkeypatch):
    # past the warm start, which leaves these data at the noise floor: a step through the solver and
    # the last layer's refinement too
    monkeypatch.setattr(recipe, "TRAIN_AT_FLOOR", True)
    fmu = example_fmu("dc_drive")
    (tmp_path / "workflow").mkdir()
    trained = _trained_by_the_workflow(fmu, windage, tmp_path / "workflow")
    try:
        expected = [p.detach().clone() for p in trained.model.topology.parameters()]
        expected_settings = trained.metrics["settings"]
    finally:
        trained.model.close()
    output = tmp_path / "trained.neuralfmu"
    assert cli.run(["train", str(fmu), "--data", str(windage), "--recipe", "hybridize", "--target", CHANNEL,
                    "--inputs", ",".join(INPUTS), "--loss", ",".join(LOSS), "--budget", "1", "--seed", "0",
                    "--quiet", "-o", str(output)]) == 0
    model = load_neural_fmu(output)
    try:
        got = [p.detach() for p in model.topology.parameters()]
    finally:
        model.close()
    assert len(got) == len(expected)
    assert all(torch.allclose(a, b, rtol=1e-6, atol=1e-9) for a, b in zip(got, expected))
    assert expected_settings["optimizer"] == "lbfgs" and expected_settings["solver"] == "rk4"
    assert trained.metrics["loss_evaluations"] == 1 and trained.metrics["last_layer"]
