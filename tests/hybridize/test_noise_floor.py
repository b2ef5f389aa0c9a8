"""The scoring's integrator error lies below the measurement noise (`Scoring.checked`), and a
simulation started from measured data starts where the data say (`measured_initial_states`).

References: the truth FMU that generated the data (it must score at the noise floor, the
generator's noise variance, on every signal), DOPRI5 at a tight tolerance for the checked step,
and the known start of synthetic data.
"""
from types import SimpleNamespace

import numpy as np
import pytest

import fmubuilder.hybridize.evaluate as scoring_module
from fmubuilder import synth
from fmubuilder.build import example_fmu
from fmubuilder.data import START_SAMPLES, MeasuredData
from fmubuilder.examples_zoo import DC_DRIVE_BENCH
from fmubuilder.fmi import read_model_info
from fmubuilder.hybridize.evaluate import Scoring, evaluate, read_data
from fmubuilder.neural.train import measured_initial_states

TRUTH = "dc_drive_truth_extra_heating"
RUNS = 2


def noise_floor(signal: str) -> float:
    """The generator's noise variance of the measured value (mean over the runs)."""
    return DC_DRIVE_BENCH["noise_std"][signal] ** 2 / RUNS


def measured(folder, stop: float, seed: int):
    settings = synth.BenchSettings(seed=seed, runs=RUNS, **DC_DRIVE_BENCH)
    measurement = synth.measure(example_fmu(TRUTH), start_time=0.0, stop_time=stop, settings=settings)
    path = folder / f"{TRUTH}_{stop:g}_{seed}.csv"
    synth.write_measurement(measurement, path)
    return read_data(path, read_model_info(example_fmu("dc_drive")))


@pytest.fixture(scope="module")
def short_data(tmp_path_factory):
    return measured(tmp_path_factory.mktemp("noise_floor"), 10.0, seed=8)


def test_a_step_too_large_is_halved_until_h_and_h_over_2_agree_within_the_noise(short_data, monkeypatch):
    # Started at the sample period (0.1 s) the RK4 run of the DC drive is far off (it runs away).
    monkeypatch.setattr(scoring_module, "FIRST_STEP_SHARE", 1.0)
    scoring = Scoring.checked(example_fmu("dc_drive"), short_data, {})
    assert scoring.solver == "rk4" and scoring.halvings >= 1
    assert scoring.step == pytest.approx(0.1 / 2 ** scoring.halvings)
    assert scoring.check <= scoring_module.STEP_TOLERANCE
    assert "checked: h/2 differs by < 0.1 noise" in scoring.describe()
    # Independently: the chosen step against DOPRI5 at a tight tolerance.
    fmu = example_fmu("dc_drive")
    chosen = evaluate(fmu, short_data, {}, scoring)
    reference = evaluate(fmu, short_data, {}, Scoring("dopri5", 1e-3))
    for name in short_data.names:
        error = np.mean((chosen.predicted[name] - reference.predicted[name]) ** 2) / short_data.noise_variance(name)
        assert error < 2 * scoring_module.STEP_TOLERANCE, name


def test_the_halving_stops_at_the_cap(short_data, monkeypatch):
    monkeypatch.setattr(scoring_module, "STEP_TOLERANCE", 1e-30)     # no step is good enough
    first = scoring_module.first_step(short_data)
    scoring = Scoring.checked(example_fmu("dc_drive"), short_data, {})
    assert scoring.halvings == scoring_module.MAX_HALVINGS
    assert scoring.step == pytest.approx(first / 2 ** scoring_module.MAX_HALVINGS)
    assert "still differs" in scoring.describe()


def test_the_first_step_is_a_tenth_of_the_sample_period_rounded_down():
    for period, step in ((0.1, 0.01), (0.0999, 0.01), (0.3, 0.02), (0.07, 0.005), (1.0, 0.1)):
        time = np.arange(50) * period
        assert scoring_module.first_step(MeasuredData(time, {"x": time})) == pytest.approx(step)


def test_the_truth_scores_at_the_noise_floor_with_the_checked_step_and_not_with_euler(tmp_path):
    data = measured(tmp_path, 30.0, seed=8)
    info = read_model_info(example_fmu("dc_drive"))
    checked = Scoring.checked(example_fmu("dc_drive"), data, {})
    truth = evaluate(example_fmu(TRUTH), data, {}, checked).errors
    for name in data.names:
        assert 0.7 <= truth[name]["mse"] / noise_floor(name) <= 1.4, (name, truth[name]["mse"] / noise_floor(name))
    # Explicit Euler at the FMU's DefaultExperiment step: the temperature, slow and integrating,
    # carries an integrator error above the noise.
    euler = evaluate(example_fmu(TRUTH), data, {}, Scoring.fmu_step(info, data)).errors
    assert euler["temperature"]["mse"] / noise_floor("temperature") > 2.0


def _stand_in_model(start: float):
    """What measured_initial_states reads of a NeuralFMU: its states and their start values."""
    info = SimpleNamespace(variable=lambda name: SimpleNamespace(start=start))
    return SimpleNamespace(info=info, start_values={}, state_names=lambda: ["x"])


@pytest.mark.parametrize("offset", [0.0, 0.5])
def test_a_run_starts_at_the_model_start_unless_the_first_seconds_of_data_say_otherwise(offset):
    rng = np.random.default_rng(4)
    time = np.arange(0.0, 5.0, 0.1)
    true_start, noise = 2.0 + offset, 0.05
    values = true_start + 0.4 * time + noise * rng.standard_normal(time.size)
    data = MeasuredData(time, {"x": values})
    start = measured_initial_states(_stand_in_model(2.0), data)["x"]
    if offset == 0.0:
        assert start == 2.0                    # the data agree with the model: its exact value
    else:
        # a line through the first samples (numpy's polyfit as the reference), not the first sample
        line = np.polyfit(time[:START_SAMPLES], values[:START_SAMPLES], 1)
        assert start == pytest.approx(line[1], rel=1e-12)
        assert start != pytest.approx(values[0], abs=1e-6)


def test_an_element_start_keeps_the_runs_state_where_the_data_agree():
    rng = np.random.default_rng(5)
    time = np.arange(0.0, 10.0, 0.1)
    values = np.sin(0.3 * time) + 0.01 * rng.standard_normal(time.size)
    data = MeasuredData(time, {"x": values})
    model = _stand_in_model(0.0)
    at = 4.0
    assert measured_initial_states(model, data, at, {"x": np.sin(0.3 * at)})["x"] == np.sin(0.3 * at)
    moved = measured_initial_states(model, data, at, {"x": np.sin(0.3 * at) + 0.2})["x"]
    first = int(np.searchsorted(time, at - 1e-9))
    line = np.polyfit(time[first:first + START_SAMPLES] - at, values[first:first + START_SAMPLES], 1)
    assert moved == pytest.approx(line[1], rel=1e-12)
    assert abs(moved - np.sin(0.3 * at)) < 0.03


@pytest.mark.parametrize("offset", [1.5, 10.0])
def test_samples_that_happen_to_lie_on_a_line_do_not_outweigh_the_noise_the_data_state(offset):
    """A handful of noisy samples can lie close to a line by chance, and their residuals alone then
    call a start a noise deviation or two away wrong: the run starts at a noisy sample's offset (and
    a training from it learns to make that offset up). The data's spread columns say how noisy a
    sample is; a start that far from the line is kept, one ten deviations away is not."""
    time = np.arange(0.0, 5.0, 0.1)
    runs, deviation = 2, 0.7                         # the noise of the measured value (mean over the runs)
    values = offset * deviation + 0.4 * time          # on a line: the residuals are zero
    spread = {"x": np.full(time.size, deviation * np.sqrt(runs))}
    line = np.polyfit(time[:START_SAMPLES], values[:START_SAMPLES], 1)[1]
    without_spread = measured_initial_states(_stand_in_model(0.0), MeasuredData(time, {"x": values}))["x"]
    assert without_spread == pytest.approx(line, rel=1e-12)          # nothing says the samples are noisy
    start = measured_initial_states(_stand_in_model(0.0), MeasuredData(time, {"x": values}, std=spread, runs=runs))["x"]
    assert start == (0.0 if offset < 3 else pytest.approx(line, rel=1e-12))


def test_a_start_read_along_the_runs_course_is_not_biased_by_its_curve():
    """A speed braking to a halt within the first samples (as the VLDM's after 900 s): a line through
    the samples misses the start by the curve (on the VLDM by 3.4 noise deviations, and the driver's
    controller answered with a 10 kW spike on the power). Read along the run's own course (the data
    minus the run's change, then the line), the estimate is unbiased: over 400 noise draws its mean
    lies within 3 standard errors of the true start, where the line's lies 8 standard errors off.
    The run here starts 1.0 away (its course shifted), so the data always overrule its start."""
    time = np.arange(0.0, 5.0, 0.1)
    course = lambda t: 23.4 + 0.1 * np.exp(-np.asarray(t) / 0.15)      # noqa: E731
    noise, draws = 0.01, 400
    model = _stand_in_model(0.0)
    along, line = [], []
    for seed in range(draws):
        values = course(time) + noise * np.random.default_rng(seed).standard_normal(time.size)
        data = MeasuredData(time, {"x": values})
        wrong = {"x": float(course(0.0)) + 1.0}
        along.append(measured_initial_states(model, data, 0.0, wrong, model_runs={"x": (time, course(time) + 1.0)})["x"])
        line.append(measured_initial_states(model, data, 0.0, wrong)["x"])
    for estimates, biased in [(along, False), (line, True)]:
        estimates = np.asarray(estimates)
        standard_error = estimates.std(ddof=1) / np.sqrt(draws)
        offset = abs(estimates.mean() - course(0.0)) / standard_error
        assert (offset > 8.0) if biased else (offset < 3.0)
