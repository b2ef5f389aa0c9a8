"""The data's three roles, the choice on validation, and numbers that do not depend on the clock.

- training samples and validation samples do not overlap; by default the validation part is the
  late share of each training run, and the fit (diagnosis, NeuralFMU) sees only the rest;
- the candidate is chosen on validation, never on the test data, and every candidate's test
  numbers are reported;
- the same command writes the same report.json numbers on an idle and on a busy machine.
"""
import argparse
import json
import subprocess
import sys
import time

import numpy as np
import pytest

from fmubuilder import synth
from fmubuilder.build import example_fmu
from fmubuilder.fmi import read_model_info
from fmubuilder.fmi.side_process import can_run_beside
from fmubuilder.hybridize import hybridize, recipe
from fmubuilder.cli.hybridize import add_hybridize_parser
from fmubuilder.hybridize.workflow import VALIDATION_SHARE, Scores, _assign_roles, _select

BENCH = dict(signals=("speed", "current", "power", "temperature"),
             noise_std={"speed": 0.1, "current": 0.02, "power": 1.0, "temperature": 0.02})
TRUTH = "dc_drive_truth_windage"


def measure(folder, window, seed):
    settings = synth.BenchSettings(seed=seed, **BENCH)
    measurement = synth.measure(example_fmu(TRUTH), start_time=window[0], stop_time=window[1], settings=settings)
    return synth.write_measurement(measurement, folder / f"{window[0]:g}-{window[1]:g}_{seed}.csv")


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("roles")
    return {"train": measure(folder, (0.0, 10.0), 0), "more": measure(folder, (10.0, 16.0), 3),
            "test": measure(folder, (20.5, 26.0), 1)}


def test_validation_is_the_late_share_of_each_training_run_and_disjoint_from_the_fit(files):
    info = read_model_info(example_fmu("dc_drive"))
    roles = _assign_roles(info, [files["train"], files["more"]], [{}, {"speed": "0.0"}], None, None,
                          files["test"], None)
    assert roles.held_out_of_training and len(roles.train) == len(roles.validation) == 2
    for fit, held_out in zip(roles.train, roles.validation):
        assert fit.data is held_out.data
        fit_time, held_time = fit.samples().time, held_out.samples().time
        assert fit_time[-1] < held_time[0]                      # no sample in both
        assert fit_time.size + held_time.size == fit.data.time.size
        span = fit.data.stop - fit.data.start
        assert held_out.window[0] - fit.data.start == pytest.approx((1 - VALIDATION_SHARE) * span, abs=0.2)
    assert roles.train[1].start_values == {"speed": "0.0"}     # per file
    separate = _assign_roles(info, files["train"], None, files["more"], None, files["test"], None)
    assert not separate.held_out_of_training
    assert separate.train[0].window == (separate.train[0].data.start, separate.train[0].data.stop)
    assert separate.validation[0].data.path == files["more"]


def scores(validation_mse, test_mse):
    errors = lambda mse: {"speed": {"mse": mse, "max_abs": 0.0, "final": 0.0}}  # noqa: E731
    return Scores(fmu=None, errors={"validation": errors(validation_mse), "test": errors(test_mse)})


class FakeCandidate:
    def __init__(self, name, validation_mse, test_mse):
        self.name, self.scores = name, scores(validation_mse, test_mse)


def test_the_choice_follows_validation_even_when_the_test_data_would_disagree():
    plain = scores(1.0, 1.0)
    a, b = FakeCandidate("a", 0.5, 0.9), FakeCandidate("b", 0.6, 0.1)
    selection = _select([a, b], plain)
    assert selection["on"] == "validation" and selection["chosen"] == "a"
    assert selection["scores"] == {"a": 0.5, "b": pytest.approx(0.6)}
    assert _select([FakeCandidate("c", 1.2, 0.1)], plain)["chosen"] is None   # not published


def test_train_start_values_belong_to_the_train_file_before_them():
    parser = argparse.ArgumentParser()
    add_hybridize_parser(parser.add_subparsers())
    args = parser.parse_args(["hybridize", "m.fmu", "--train", "a.csv", "--train-start", "x=1", "--train-start", "y=2",
                              "--train", "b.csv", "--train-start", "x=3", "--test", "t.csv", "-o", "h.fmu",
                              "--report", "r"])
    assert args.train == [("a.csv", ["x=1", "y=2"]), ("b.csv", ["x=3"])]
    assert args.budget > 0 and args.time_budget is None


HYBRIDIZE = ["hybridize", "m.fmu", "--train", "a.csv", "--test", "t.csv", "-o", "h.fmu", "--report", "r"]


def test_the_training_budget_is_a_count_of_loss_evaluations_on_the_command_line(capsys):
    from fmubuilder.cli import build_parser
    assert build_parser().parse_args([*HYBRIDIZE, "--budget", "3"]).budget == 3
    for bad in ("-1", "2.5", "ten"):
        with pytest.raises(SystemExit) as stopped:
            build_parser().parse_args([*HYBRIDIZE, "--budget", bad])
        assert stopped.value.code == 2
        error = capsys.readouterr().err
        assert error.startswith("error: argument --budget") and error.count("\n") == 1 and "Traceback" not in error


def test_train_takes_epochs_or_a_budget_not_both(capsys):
    from fmubuilder.cli import build_parser
    train = ["train", "m.fmu", "--data", "d.csv", "--target", "der(v)", "--inputs", "v", "-o", "t.pt"]
    assert build_parser().parse_args([*train, "--budget", "4"]).budget == 4   # the budget counts, not the epochs
    for work in (["--epochs", "30", "--budget", "4"], ["--budget", "-1"]):
        with pytest.raises(SystemExit) as stopped:
            build_parser().parse_args([*train, *work])
        assert stopped.value.code == 2
        error = capsys.readouterr().err
        assert error.startswith("error: argument") and error.count("\n") == 1

def strip_wall_times(report: dict) -> dict:
    report = json.loads(json.dumps(report))
    for key in ("seconds", "timings", "hybrid_fmu", "model_fmu", "plots"):
        report.pop(key)
    for model in report["models"]:
        model.pop("training_seconds", None)
    return report


def run_small(files, folder, **options):
    options = {"ann_on_term": False, "progress": False, **options}
    return hybridize(example_fmu("dc_drive"), files["train"], files["test"], folder / "hybrid.fmu",
                     folder / "report", budget=2, time_budget=600.0, **options)


@pytest.fixture
def busy_cores():
    """A process spinning while the test runs (started here, stopped by its pid)."""
    spinners = [subprocess.Popen([sys.executable, "-c", "while True: pass"])]
    time.sleep(0.5)
    yield
    for spinner in spinners:
        spinner.kill()
        spinner.wait()


@pytest.fixture
def trains_at_floor(monkeypatch):
    """The training through the solver runs even where the warm start leaves the noise floor (these
    data: every signal there), so that its work is what the busy machine must not change."""
    monkeypatch.setattr(recipe, "TRAIN_AT_FLOOR", True)


@pytest.fixture
def idle_report(files, tmp_path, trains_at_floor):
    return run_small(files, tmp_path / "idle").report


def test_the_same_command_gives_the_same_numbers_on_a_busy_machine(files, tmp_path, idle_report, busy_cores):
    busy = run_small(files, tmp_path / "busy").report
    assert busy["training"]["loss_evaluations"] == idle_report["training"]["loss_evaluations"] == 2
    assert not busy["training"]["cut_short_by_time_budget"]
    assert strip_wall_times(busy) == strip_wall_times(idle_report)
    # the report says which numbers chose and which were touched once
    selection = busy["selection"]
    assert selection["on"] == "validation"
    assert set(selection["scores"]) == {m["name"] for m in busy["models"]}
    assert all(np.isfinite(m["test_relative_mse"]) for m in busy["models"])   # chosen or not
    markdown = (tmp_path / "busy" / "report" / "report.md").read_text()
    assert "touched once" in markdown and "validation score (chooses)" in markdown
    # the NeuralFMU's settings and the command that trains it again on its own
    training = busy["training"]
    assert training["settings"]["optimizer"] == "lbfgs" and training["settings"]["budget"] == 2
    assert "--recipe hybridize" in training["command"] and "--budget 2 --seed 0" in training["command"]
    assert training["command"] in markdown


@pytest.mark.skipif(not can_run_beside(), reason="no second process on this platform")
def test_the_neuralfmu_trained_in_a_second_process_gives_the_same_numbers(files, tmp_path, capsys):
    """jobs=2 trains the NeuralFMU and calibrates beside the fitted term; jobs=1 one after the other."""
    beside = run_small(files, tmp_path / "beside", jobs=2, progress=True).report
    said = capsys.readouterr().out
    assert "in a second process" in said
    assert "calibrating viscous_friction" in said      # the second process's messages reach the console
    after = run_small(files, tmp_path / "after", jobs=1, progress=True).report
    said = capsys.readouterr().out
    assert "in a second process" not in said and "calibrating viscous_friction" in said
    assert [m["name"] for m in beside["models"]] == ["fitted term", "calibrated viscous_friction", "neural"]
    assert strip_wall_times(beside) == strip_wall_times(after)


def test_a_time_cap_that_cuts_the_training_short_is_reported(files, tmp_path, trains_at_floor):
    report = hybridize(example_fmu("dc_drive"), files["train"], files["test"], tmp_path / "h.fmu", tmp_path / "r",
                       budget=1000, time_budget=1.0, ann_on_term=False, progress=False).report
    assert report["training"]["cut_short_by_time_budget"]
    assert report["training"]["loss_evaluations"] < 1000
    assert "cut it short" in (tmp_path / "r" / "report.md").read_text()
