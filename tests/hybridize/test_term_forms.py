"""The fitted term's form chosen among the leading variables' forms (fmubuilder/hybridize/term_forms.py):
forms read back from the diagnosis' text, the choice's rule, and a pair of forms fitted through the
simulation against the coefficients in the truth's C source."""
import math

import numpy as np
import pytest

from fmubuilder import synth
from fmubuilder.build import example_fmu
from fmubuilder.data import load_data
from fmubuilder.diagnose.diagnosis import candidate_of
from fmubuilder.diagnose.runs import form_text
from fmubuilder.diagnose.trace import Trial
from fmubuilder.examples_zoo import SENSOR_NOISE
from fmubuilder.fmi import read_model_info
from fmubuilder.hybridize.evaluate import Scoring
from fmubuilder.hybridize.term_forms import FormFit, choose_form, fit_forms, term_of
from fmubuilder.hybridize.workflow import Part

# examples/vldm/model.c, VLDM_TRUTH_EXTRA_RESISTANCE: F = 1.5 v + 0.06 v|v| [N], the declared model lacks it
EXTRA_DRAG_LINEAR, EXTRA_DRAG_QUADRATIC = 1.5, 0.06


@pytest.mark.parametrize("center", [0.0, 128.0, -2.5, 1.25e-7])
@pytest.mark.parametrize("basis", ["w", "|w|", "w*|w|", "w^2"])
def test_a_diagnosis_candidate_becomes_its_trials_term_with_the_exact_center(basis, center):
    """The center is the trial's own number, not the 6 digits of the form's text."""
    info = read_model_info(example_fmu("vldm"))
    channel = next(k for k, d in enumerate(info.derivatives) if d.name == "der(speed)")
    center += math.pi * 1e-9        # digits the text does not show
    trial = Trial(channel=channel, variable="motor_torque_limit", basis=basis, center=center,
                  by_signal=np.zeros(1), by_precision=np.zeros(1), score=0.5, shape_score=0.5, coefficient=-3.0)
    term = term_of(candidate_of(info, trial))
    assert term == {"variable": "motor_torque_limit", "basis": basis, "center": center, "coefficient": -3.0,
                    "form": form_text("motor_torque_limit", basis, center)}


def fit(label, coefficients, score):
    terms = [{"variable": "v", "basis": "w", "center": 0.0, "coefficient": c} for c in coefficients]
    return FormFit(label, terms, list(coefficients), 1.0, score, 1)


def test_the_diagnosis_term_stays_unless_a_form_beats_it_by_the_margin():
    diagnosed = fit("diagnosed", [1.0], 18.4)
    assert choose_form([diagnosed, fit("other", [1.0], 12.4), fit("pair", [1.0, 1.0], 11.6)], 3.2) is diagnosed
    # one coefficient first, then two against the one kept (the VLDM's scores)
    single, pair = fit("speed", [1.0], 349.0), fit("speed pair", [1.0, 1.0], 1.23)
    assert choose_form([fit("diagnosed", [1.0], 650.0), single, pair], 1.19) is pair
    assert choose_form([fit("diagnosed", [1.0], 650.0), single, fit("pair", [1.0, 1.0], 300.0)], 1.19) is single
    # a diagnosis' term that does not simulate gives way to any form that does; none: None
    assert choose_form([fit("diagnosed", [1.0], math.inf), single], 1.19) is single
    assert choose_form([fit("diagnosed", [1.0], math.inf)], 1.19) is None


def test_a_pair_of_forms_fitted_through_the_simulation_finds_the_truths_resistance(tmp_path):
    """The VLDM's extra resistance, measured over 200 s of the CADC road cycle: the pair v, v|v| on
    der(speed), started at half and twice the truth's coefficients, ends within 3 % of them (the force
    over the car's mass times its mass factor), and scores better on the held-out tail than the
    start did; a form the effect does not have (v alone) stays far above it there."""
    truth = example_fmu("vldm_truth_extra_resistance")
    measurement = synth.measure(truth, stop_time=200.0, start_values={"cycle": 1},
                                settings=synth.BenchSettings(seed=3, signals=("speed", "power", "energy"),
                                                             **SENSOR_NOISE))
    path = tmp_path / "cadc.csv"
    synth.write_measurement(measurement, path)
    model = example_fmu("vldm")
    info = read_model_info(model)
    data = load_data(path, info)
    start = {"cycle": 1}
    train = Part(data, start, (0.0, 160.0))
    validation = Part(data, start, (float(data.time[data.time > 160.0][0]), data.stop))
    mass = float(info.variable("mass").start) * float(info.variable("mass_factor").start)
    exact = [-EXTRA_DRAG_LINEAR / mass, -EXTRA_DRAG_QUADRATIC / mass]
    pair = [{"variable": "speed", "basis": "w", "center": 0.0, "coefficient": 0.5 * exact[0]},
            {"variable": "speed", "basis": "w*|w|", "center": 0.0, "coefficient": 2.0 * exact[1]}]
    single = [{"variable": "speed", "basis": "w", "center": 0.0, "coefficient": exact[0]}]
    noise = {name: math.sqrt(data.noise_variance(name)) for name in data.names}
    fits = fit_forms(model, "der(speed)", {"pair": pair, "speed": single}, [(train.samples(), start)], [validation],
                     Scoring("rk4", 0.01), noise, {}, show=False)
    fitted_pair, fitted_single = fits
    assert [t["coefficient"] for t in fitted_pair.terms] == [pytest.approx(c, rel=0.03) for c in exact]
    assert fitted_pair.validation_score < 3.0 < fitted_single.validation_score
    assert fitted_pair.simulations <= 11 and fitted_pair.training_objective < fitted_single.training_objective


def test_a_form_no_neuralfmu_can_hold_is_scored_as_not_simulating():
    """A variable the model does not have (or one a NeuralFMU cannot read) fails that form alone."""
    forms = {"unknown": [{"variable": "no_such_variable", "basis": "w", "center": 0.0, "coefficient": 1.0}]}
    fit, = fit_forms(example_fmu("dc_drive"), "der(speed)", forms, [], [], Scoring("rk4", 0.01), {}, {}, show=False)
    assert math.isinf(fit.training_objective) and math.isinf(fit.validation_score) and fit.simulations == 0
    assert choose_form([fit], 1.5) is None
