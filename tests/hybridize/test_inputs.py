"""The ANN's inputs chosen by held-out error (fmubuilder.hybridize.inputs), on the DC drive truths
whose effects no power law of one variable describes (examples/dc_drive/model.c):

* speed_current_loss: an electrical loss ~ |speed * current| in der(energy): the smoother needs
  both variables, and the choice must name both;
* stribeck: a friction that is a function of the speed alone in der(speed); energy and
  temperature rise through the run, so their held-out values lie outside the training range and a
  fit on them would be a fit on time: they must not be offered at all.

The reference is the truth's source: which variables the effect is a function of.
"""
import numpy as np
import pytest

from fmubuilder.build import example_fmu
from fmubuilder.data import load_data
from fmubuilder.diagnose.trace import candidate_variables
from fmubuilder.examples_zoo import cached_data, dc_drive_data_sets
from fmubuilder.fmi import read_model_info
from fmubuilder.hybridize.inputs import (choose_inputs, distinct_variables, estimate_missing_terms, outside_share,
                                         smoother_error)

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
        found[data_set.variant.key] = (channel, estimate_missing_terms(fmu, info, data, data.start_values, [channel],
                                                                       candidate_variables(info), step))
    return found


def _masks(term):
    return term.time <= SPLIT, term.time > SPLIT


def test_a_product_of_two_variables_gets_both_as_inputs(terms):
    channel, term = terms["speed_current_loss"]
    train, validation = _masks(term)
    choice = choose_inputs(term, channel, train, validation)
    assert choice.inputs[:2] == ["speed", "current"] or choice.inputs[:2] == ["current", "speed"]
    # and the pair is what carries it: either one alone predicts the held-out term far worse
    alone = [choice.steps[0]["validation_error"]]
    assert choice.steps[1]["validation_error"] < 0.7 * alone[0]
    assert choice.explained > 0.6
    assert "power" not in choice.inputs          # equal to der(energy) in the model: its own output


def test_a_friction_of_speed_gets_speed_and_no_cumulative_variable(terms):
    channel, term = terms["stribeck"]
    train, validation = _masks(term)
    choice = choose_inputs(term, channel, train, validation)
    assert choice.inputs[0] == "speed"
    assert {"energy", "temperature"} <= set(choice.out_of_range)
    assert not {"energy", "temperature"} & set(choice.inputs)
    # a fit on the training samples alone would take the energy: it tells every sample apart
    ok = np.isfinite(term.missing[channel])
    fit_error = smoother_error(term.variables, ["energy"], train & ok, train & ok, term.missing[channel])
    held_out_error = smoother_error(term.variables, ["energy"], train & ok, validation & ok, term.missing[channel])
    assert held_out_error > 2.0 * fit_error


def test_out_of_range_share_counts_held_out_values_beyond_the_training_range():
    assert outside_share(np.array([0.0, 1.0]), np.array([0.5, 1.02, 1.2, -0.3])) == 0.5
    assert outside_share(np.arange(10.0), np.arange(10.0, 20.0)) == 1.0


def test_proportional_copies_are_one_input():
    x = np.linspace(-1.0, 1.0, 50)
    variables = {"speed": x, "friction_torque": -1e-3 * x, "current": np.cos(3 * x)}
    kept, duplicates = distinct_variables(variables, ["speed", "friction_torque", "current"], np.ones(50, bool))
    assert kept == ["speed", "current"] and duplicates == {"friction_torque": "speed"}
