"""The ANN's inputs chosen by cross-validated error with a test against noise
(fmubuilder.hybridize.inputs).

On synthetic samples whose truth is known: a product of two variables gets both, a cumulative
variable that follows the effect through the run is rejected, coloured noise admits nothing.

On the DC drive truths whose effects no power law of one variable describes
(examples/dc_drive/model.c):

* speed_current_loss: an electrical loss ~ |speed * current| in der(energy): the smoother needs
  both variables, and the choice must name both;
* stribeck: a friction that is a function of the speed alone in der(speed); energy and
  temperature rise through the run, so their held-out values lie outside the training range and a
  fit on them would be a fit on time: they must not be offered at all.

The reference is the truth's source: which variables the effect is a function of.
"""
import numpy as np
import pytest
from scipy.signal import lfilter
from scipy.spatial import cKDTree

from fmubuilder.build import example_fmu
from fmubuilder.data import first_order_lag, load_data
from fmubuilder.diagnose.trace import candidate_variables
from fmubuilder.examples_zoo import cached_data, dc_drive_data_sets
from fmubuilder.fmi import read_model_info
from fmubuilder.hybridize import inputs
from fmubuilder.neural import collocation
from fmubuilder.hybridize.inputs import (MissingTermRun, choose_inputs, contiguous_folds, cross_validated_squared_errors,
                                         distinct_variables, forward_selection, outside_share,
                                         paired_t, time_blocks)
from fmubuilder.simulation.results import sample_settled

SPLIT = 48.0        # the workflow's split of the 60 s training run: 80 % to fit, the rest held out


@pytest.fixture(scope="module")
def terms():
    """Missing-term estimates along the training runs of the two truths."""
    sets = [s for s in dc_drive_data_sets() if s.cycle.role == "train"
            and s.variant.key in ("stribeck", "speed_current_loss")]
    paths, _ = cached_data(sets)
    fmu = example_fmu("dc_drive")
    info = read_model_info(fmu)
    found = {}
    for data_set, path in zip(sets, paths):
        data = load_data(path, info)
        channel = {"stribeck": "der(speed)", "speed_current_loss": "der(energy)"}[data_set.variant.key]
        step = info.default_experiment.step_size
        run = MissingTermRun(fmu, info, data, data.start_values, candidate_variables(info), step)
        found[data_set.variant.key] = (channel, run.estimate([channel]))
    return found


def _masks(term):
    return term.time <= SPLIT, term.time > SPLIT


def test_a_product_of_two_variables_gets_both_as_inputs(terms):
    channel, term = terms["speed_current_loss"]
    train, validation = _masks(term)
    choice = choose_inputs(term, channel, train, validation)
    assert sorted(choice.inputs) == ["current", "speed"]
    # and the pair is what carries it: the second input lowers the error of the first alone
    assert choice.steps[1]["cv_error"] < 0.9 * choice.steps[0]["cv_error"]
    assert choice.explained > 0.6
    assert "power" not in choice.inputs          # equal to der(energy) in the model: its own output


def test_the_estimated_loss_is_the_truths_within_the_power_sensors_noise(terms):
    """The estimate of der(energy) against the loss along the truth's own run (seen through the
    sensors' lag, as the estimate compares): the measured power, equal to der(energy) in the model,
    gives it without the energy's slope, whose noise was 0.3 of the loss' size."""
    from fmubuilder.simulation import simulate
    channel, term = terms["speed_current_loss"]
    data_set = next(s for s in dc_drive_data_sets() if s.cycle.role == "train" and s.variant.key == "speed_current_loss")
    truth_fmu = example_fmu("dc_drive_truth_speed_current_loss")
    truth = simulate(truth_fmu, start_time=term.time[0], stop_time=term.time[-1], variables=["speed", "current"],
                     start_values=data_set.start_values, solver="rk4", step_size=0.001, output_interval=0.001)
    time = np.asarray(truth.time)
    loss = 0.01 * np.abs(np.asarray(truth["speed"]) * np.asarray(truth["current"]))   # model.c SPEED_CURRENT_LOSS
    seen = np.interp(term.time, time, first_order_lag(time, loss, 0.1))                 # the bench's sensor lag
    error = term.missing[channel] - seen
    assert np.all(np.isfinite(error))
    assert abs(np.mean(error)) < 0.05 * np.sqrt(np.mean(seen ** 2))
    assert np.sqrt(np.mean(error ** 2)) < 0.2 * np.sqrt(np.mean(seen ** 2))


def test_a_friction_of_speed_gets_speed_alone_and_no_cumulative_variable(terms):
    channel, term = terms["stribeck"]
    train, validation = _masks(term)
    choice = choose_inputs(term, channel, train, validation)
    assert choice.inputs == ["speed"]
    assert {"energy", "temperature"} <= set(choice.out_of_range)
    # a fit on the samples themselves would take the energy: it tells every sample apart; on
    # contiguous folds it predicts no better than the mean
    ok = np.isfinite(term.missing[channel]) & (train | validation)
    energy, missing = term.variables["energy"][ok], term.missing[channel][ok]
    assert _in_sample_error(energy, missing, k=5) < 0.5 * np.var(missing)
    standardised = (energy - np.mean(energy)) / np.std(energy)
    assert (np.mean(cross_validated_squared_errors(standardised[:, None], missing))
            >= np.mean(cross_validated_squared_errors(None, missing)))


def test_a_second_set_of_channels_reuses_the_runs_and_equals_a_fresh_estimate(monkeypatch):
    """The loop's second estimate (the measured derivatives besides the channel) costs no
    simulation once the first needed the plain run (der(energy) reads the controller's unmeasured
    integrator), and equals an estimate of its own, which simulates both runs again. The plain run
    is done once, by the engine, for the forced run's integrators and the comparison alike; it
    agrees with the batch solver's at the same step."""
    data_set = next(s for s in dc_drive_data_sets() if s.cycle.role == "train" and s.variant.key == "windage")
    path, = cached_data([data_set])[0]
    fmu = example_fmu("dc_drive")
    info = read_model_info(fmu)
    data = load_data(path, info)
    data = data.window(data.start, data.start + 5.0)
    step = info.default_experiment.step_size
    simulations = []
    for module, name in ((inputs, "_forced_run"), (inputs, "_plain_run"), (collocation, "_run")):
        real = getattr(module, name)
        monkeypatch.setattr(module, name, lambda *a, _real=real, _name=name, **k: simulations.append(_name) or _real(*a, **k))
    run = MissingTermRun(fmu, info, data, data.start_values, candidate_variables(info), step)
    run.estimate(["der(energy)"])
    assert simulations == ["_plain_run", "_forced_run", "_run"]     # the batch solver runs the forced run only
    channels = ["der(speed)", "der(energy)", "der(current)"]
    shared = run.estimate(channels)
    assert len(simulations) == 3
    fresh = MissingTermRun(fmu, info, data, data.start_values, candidate_variables(info), step).estimate(channels)
    assert len(simulations) == 6
    assert list(shared.missing) == list(fresh.missing) == channels
    for c in channels:
        np.testing.assert_array_equal(shared.missing[c], fresh.missing[c])
    assert list(shared.variables) == list(fresh.variables)
    for name in fresh.variables:
        np.testing.assert_array_equal(shared.variables[name], fresh.variables[name])
    assert shared.aliases == fresh.aliases and shared.kinds == fresh.kinds and shared.measured == fresh.measured
    grid, batch = inputs._forced_run(fmu, info, data, data.start_values, {}, ["der(energy)"], step, "euler")
    lagged = first_order_lag(grid, batch["der(energy)"], data.sensor_lag)
    time, plain = run._plain
    engine = sample_settled(time, first_order_lag(time, plain["der(energy)"], data.sensor_lag), grid)
    assert np.max(np.abs(engine - lagged)) <= 1e-6 * np.max(np.abs(lagged))


# -- synthetic samples: the truth is known ----------------------------------------------------------

STEP = 0.1                       # 10 Hz samples, 60 s, as the DC drive's data
TIME = np.arange(600) * STEP


def _coloured_noise(rng, tau=0.2):
    """Unit-variance noise through a first-order low-pass of time constant tau (a filtered sensor)."""
    a = np.exp(-STEP / tau)
    return lfilter([1.0 - a], [1.0, -a], rng.standard_normal(TIME.size)) / np.sqrt((1.0 - a) / (1.0 + a))


def _smooth_signal(rng):
    """A sum of three slow sines of random frequency and phase: revisits its values through the run."""
    frequencies, phases = rng.uniform(0.05, 0.4, 3), rng.uniform(0.0, 2 * np.pi, 3)
    return sum(np.sin(2 * np.pi * f * TIME + p) for f, p in zip(frequencies, phases))


def _in_sample_error(x, y, k=20):
    """MSE of a k-nearest-neighbour mean fitted and scored on the same samples."""
    _, index = cKDTree(x[:, None]).query(x[:, None], k=k)
    return float(np.mean((y - y[index].mean(axis=1)) ** 2))


def _interleaved_error(x, y, k=20, folds=5):
    """MSE of a k-nearest-neighbour mean under cross-validation with interleaved folds (every
    fifth sample): neighbours in time are in the other folds."""
    predicted = np.empty_like(y)
    for f in range(folds):
        held_out = np.arange(y.size) % folds == f
        _, index = cKDTree(x[~held_out, None]).query(x[held_out, None], k=k)
        predicted[held_out] = y[~held_out][index].mean(axis=1)
    return float(np.mean((y - predicted) ** 2))


@pytest.mark.parametrize("seed", range(4))
def test_synthetic_product_of_two_variables_gets_both_and_no_distractor(seed):
    rng = np.random.default_rng(seed)
    speed, current, other = (_smooth_signal(rng) for _ in range(3))
    effect = np.abs(speed * current)
    target = effect + 0.1 * np.std(effect) * _coloured_noise(rng)
    variables = {"speed": speed, "current": current, "other": other, "noise": _coloured_noise(rng)}
    selection = forward_selection(variables, target, TIME)
    assert sorted(selection.inputs) == ["current", "speed"]
    assert all(step["t"] >= 3.0 for step in selection.steps)


@pytest.mark.parametrize("seed", range(3))
def test_synthetic_product_gets_the_measured_pair_over_a_square_the_model_computes(seed):
    """|speed * current| with the model's copper loss (~ current^2) among the candidates: the square
    folds the current's sign, which the effect ignores, so the smoother fits closer with it; the
    variables the data measure win when they pass both tests too."""
    rng = np.random.default_rng(seed)
    speed, current = _smooth_signal(rng), _smooth_signal(rng)
    effect = np.abs(speed * current)
    target = effect + 0.1 * np.std(effect) * _coloured_noise(rng)
    variables = {"speed": speed, "current": current, "copper_loss": 1.2 * current ** 2,
                 "speed_error_integral": 0.1 * speed + 1.2 * current}
    assert sorted(forward_selection(variables, target, TIME).inputs) == ["copper_loss", "speed"]
    selection = forward_selection(variables, target, TIME, measured={"speed", "current"})
    assert sorted(selection.inputs) == ["current", "speed"]
    assert all(step["t"] >= 3.0 for step in selection.steps)


@pytest.mark.parametrize("seed", range(4))
def test_synthetic_cumulative_variable_that_follows_the_effect_is_rejected(seed):
    rng = np.random.default_rng(seed)
    # a speed that stays positive and drifts up: its angle grows through the run like time
    speed = 50 + 30 * np.sin(2 * np.pi * TIME / 7.0) + 15 * np.sin(2 * np.pi * TIME / 17.3 + seed) + 0.3 * TIME
    angle = np.cumsum(speed) * STEP
    effect = 1e-3 * speed ** 2
    target = effect + 0.1 * np.std(effect) * _coloured_noise(rng)
    # the angle predicts the effect when its neighbours in time are among the samples fitted ...
    assert _interleaved_error(angle, target) < 0.3 * np.var(target)
    # ... but not on a stretch of time it was not fitted on: the speed is chosen, never the angle
    assert forward_selection({"angle": angle, "speed": speed}, target, TIME).inputs == ["speed"]
    assert forward_selection({"angle": angle, "noise": _coloured_noise(rng)}, target, TIME).inputs == []


@pytest.mark.parametrize("seed", range(6))
def test_synthetic_coloured_noise_admits_nothing(seed):
    rng = np.random.default_rng(seed)
    variables = {"speed": _smooth_signal(rng), "current": _smooth_signal(rng), "random_walk": np.cumsum(
        rng.standard_normal(TIME.size)), "noise": _coloured_noise(rng)}
    selection = forward_selection(variables, _coloured_noise(rng), TIME)
    assert selection.inputs == [] and selection.error == selection.baseline


def test_contiguous_folds_and_time_blocks():
    assert contiguous_folds(10).tolist() == [0, 0, 1, 1, 2, 2, 3, 3, 4, 4]
    # a new block every BLOCK_SECONDS (1.2 s) and where a second run starts
    time = np.array([0.0, 0.5, 1.0, 1.3, 2.0, 2.6, 0.0, 0.4])
    assert time_blocks(time).tolist() == [0, 0, 0, 1, 1, 2, 3, 3]


def test_paired_t_against_a_direct_computation():
    rng = np.random.default_rng(0)
    blocks = np.repeat(np.arange(8), 5)
    old, new = rng.uniform(1.0, 2.0, 40), rng.uniform(0.5, 1.5, 40)
    ratios = [np.log(old[blocks == b].mean() / new[blocks == b].mean()) for b in range(8)]
    expected = np.mean(ratios) / (np.std(ratios, ddof=1) / np.sqrt(8))
    assert paired_t(new, old, blocks) == pytest.approx(expected, rel=1e-12)
    assert paired_t(old, new, blocks) == pytest.approx(-expected, rel=1e-12)


def test_out_of_range_share_counts_held_out_values_beyond_the_training_range():
    assert outside_share(np.array([0.0, 1.0]), np.array([0.5, 1.02, 1.2, -0.3])) == 0.5
    assert outside_share(np.arange(10.0), np.arange(10.0, 20.0)) == 1.0


def test_proportional_copies_are_one_input():
    x = np.linspace(-1.0, 1.0, 50)
    variables = {"speed": x, "friction_torque": -1e-3 * x, "current": np.cos(3 * x)}
    kept, duplicates = distinct_variables(variables, ["speed", "friction_torque", "current"], np.ones(50, bool))
    assert kept == ["speed", "current"] and duplicates == {"friction_torque": "speed"}


def test_runs_that_each_start_at_zero_are_joined_in_increasing_time():
    """A separate validation run starts at 0 like the training run: joined, the stamps must still
    increase (the settled-sample windows and the test blocks are windows in time), and the choice on
    them must find the variable the term is made of."""
    rng = np.random.default_rng(3)

    def run(length):
        time = np.arange(0.0, length, 0.1)
        speed = np.sin(0.7 * time) + 0.3 * rng.normal(size=time.size)
        other = rng.normal(size=time.size)
        return inputs.MissingTerm(time, {"der(x)": np.tanh(3.0 * speed) + 0.05 * rng.normal(size=time.size)},
                                  {"speed": speed, "other": other, "der(x)": np.zeros(time.size)},
                                  {"speed": "state", "other": "output"}, {"speed"})
    train, validation = run(40.0), run(12.0)
    joined = inputs._joined([train, validation])
    assert np.all(np.diff(joined.time) > 0)
    assert joined.time[train.time.size] - joined.time[train.time.size - 1] > inputs.SLOPE_WINDOW
    train_mask = np.r_[np.ones(train.time.size, bool), np.zeros(validation.time.size, bool)]
    choice = inputs.choose_inputs(joined, "der(x)", train_mask, ~train_mask)
    assert choice.inputs[:1] == ["speed"]
