"""Calibration of an FMU parameter (fmubuilder/hybridize/calibrate.py) and its export (a hybrid
with the parameter's override and no network, fmubuilder/export/).

The truths are known: the data come from the same C model with one parameter changed (the
sampled plant's friction b 0.2 instead of the declared 0.05; the DC drive's winding resistance
1.32 instead of 1.2 Ohm), so the fit is compared with that value. The exported FMU is checked
in fmpy, without start values, against fmpy running the original with the calibrated value.
"""
import ctypes

import numpy as np
import pytest
from fmpy import read_model_description, simulate_fmu
from fmpy.fmi2 import FMU2Model
from fmpy.validation import validate_fmu

from fmubuilder import synth
from fmubuilder.build import example_fmu
from fmubuilder.errors import FmuBuilderError
from fmubuilder.export import HybridSpec, export_hybrid
from fmubuilder.fmi import read_model_info
from fmubuilder.hybridize import hybridize
from fmubuilder.hybridize.calibrate import (FIT_SIMULATIONS, Sensitivity, calibrate, calibratable_parameters, distinct,
                                            fit_parameter)
from fmubuilder.hybridize.evaluate import Objective, Scoring, evaluate, read_data, relative_mse
from fmubuilder.simulation import simulate

TRUE_FRICTION, DECLARED_FRICTION = 0.2, 0.05
PROFILE = ([0, 1, 1.001, 2.5, 2.501, 4], [1, 1, 2, 2, 0.5, 0.5], 4.0)
TEST_PROFILE = ([0, 1.5, 1.501, 3], [2, 2, 0.8, 0.8], 3.0)


def plant_csv(path, profile, seed, friction=TRUE_FRICTION):
    """The sampled plant with friction `friction`: speed w every 10 ms with noise, and the set point."""
    times, setpoints, stop = profile
    result = simulate(example_fmu("sampled_plant"), stop_time=stop, start_values={"b": friction},
                      inputs={"time": np.asarray(times, float), "setpoint": np.asarray(setpoints, float)},
                      solver="rk4", step_size=0.001, output_interval=0.01, variables=["w"])
    keep = np.r_[True, np.diff(result.time) > 0]
    t = result.time[keep]
    w = result["w"][keep] + 0.002 * np.random.default_rng(seed).standard_normal(t.size)
    np.savetxt(path, np.column_stack([t, w, np.interp(t, times, setpoints)]), delimiter=",",
               header="time,w,setpoint", comments="", fmt="%.10g")
    return path


@pytest.fixture(scope="module")
def plant_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("calibrate_plant")
    return plant_csv(folder / "train.csv", PROFILE, 0), plant_csv(folder / "test.csv", TEST_PROFILE, 1)


def runs_of(fmu, csv, window=None):
    info = read_model_info(fmu)
    data = read_data(csv, info)
    return info, Scoring.fmu_step(info, data), [(data.window(*window) if window else data, data.start_values)]


# ---------------------------------------------------------------------------------------
# the search: screening and fit recover a known parameter error


def test_the_friction_is_ranked_first_and_fitted_to_its_true_value(plant_files):
    fmu = example_fmu("sampled_plant")
    info, scoring, runs = runs_of(fmu, plant_files[0])
    ranked, fits = calibrate(fmu, info, runs, scoring)
    assert ranked[0].name == "b" and ranked[0].explained > 0.9
    best = min(fits, key=lambda f: f.train_score)
    assert best.name == "b"
    assert best.value == pytest.approx(TRUE_FRICTION, rel=0.01)
    assert best.train_score < 0.01          # mean MSE / MSE of the declared model
    assert best.simulations <= 8


def test_three_copies_of_a_run_fit_as_the_run_alone(plant_files):
    """The same run thrice has the same score (each signal's MSE over all runs), so the fit takes
    the same steps in the same number of simulations: one simulation is one pass over all runs."""
    fmu = example_fmu("sampled_plant")
    info, scoring, runs = runs_of(fmu, plant_files[0])
    alone = fit_parameter(fmu, runs, scoring, "b", DECLARED_FRICTION)
    thrice = fit_parameter(fmu, runs * 3, scoring, "b", DECLARED_FRICTION)
    assert thrice.simulations == alone.simulations <= FIT_SIMULATIONS
    assert thrice.value == pytest.approx(alone.value, rel=1e-9)
    assert thrice.train_score == pytest.approx(alone.train_score, rel=1e-9)
    # the score minimised is the workflow's, here from two separate simulations
    data, start_values = runs[0]
    plain = evaluate(fmu, data, start_values, scoring).errors
    fitted = evaluate(fmu, data, {**start_values, "b": alone.value}, scoring).errors
    assert alone.train_score == pytest.approx(relative_mse(plain, fitted), rel=1e-9)


def test_a_failed_pass_over_the_runs_costs_one_simulation(plant_files):
    fmu = example_fmu("sampled_plant")
    info, scoring, runs = runs_of(fmu, plant_files[0], window=(0.0, 1.0))
    data, start_values = runs[0]
    broken = (data, {**start_values, "no_such_parameter": 1.0})      # it never simulates
    for order in ([*runs, *runs, broken], [broken, *runs]):
        objective = Objective(fmu, order, scoring)
        assert objective.errors({}) is None and objective.simulations == 1
    objective = Objective(fmu, runs * 3, scoring)
    errors = objective.errors({"b": 0.1})
    assert objective.simulations == 1
    alone = evaluate(fmu, data, {**start_values, "b": 0.1}, scoring).predicted["w"] - data.signals["w"]
    np.testing.assert_array_equal(errors, np.tile(alone, 3))


def test_the_dc_drive_winding_resistance_is_recovered(tmp_path):
    fmu = example_fmu("dc_drive")
    settings = synth.BenchSettings(seed=3, signals=("speed", "current", "power", "temperature"),
                                   noise_std={"speed": 0.1, "current": 0.02, "power": 1.0, "temperature": 0.02})
    measurement = synth.measure(fmu, stop_time=6.0, settings=settings, truth_parameters={"nominal_resistance": 1.32})
    csv = tmp_path / "resistance.csv"
    synth.write_measurement(measurement, csv)
    info, scoring, runs = runs_of(fmu, csv)
    assert "nominal_resistance" not in runs[0][1]        # the data do not give the truth away
    ranked, fits = calibrate(fmu, info, runs, scoring)
    # The resistance is R0 (1 + alpha (T - T_ref)): near T_ref, moving T_ref by -25 K is the same
    # +10 %, so both may be fitted; the resistance itself must come out right.
    resistance = next(f for f in fits if f.name == "nominal_resistance")
    assert resistance.value == pytest.approx(1.32, rel=0.02)
    assert {f.name for f in fits} <= {"nominal_resistance", "reference_temperature"}
    # alike, not the same: the warming winding tells them apart, so neither hides the other
    assert not any(s.equivalent for s in ranked[:2])


def test_parameters_that_act_alike_are_fitted_once(tmp_path):
    """The VLDM's air drag is 0.5 * air_density * drag_coefficient * frontal_area * v^2, its rolling
    resistance mass * gravity * rolling_coefficient (on a flat road gravity enters nowhere else):
    the factors of one product are one candidate, fitted once."""
    settings = synth.BenchSettings(seed=0, signals=("speed", "power", "energy"))
    measurement = synth.measure(example_fmu("vldm_truth_extra_resistance"), stop_time=30.0,
                                start_values={"cycle": 1}, settings=settings)
    csv = tmp_path / "vldm.csv"
    synth.write_measurement(measurement, csv)
    fmu = example_fmu("vldm")
    info = read_model_info(fmu)
    data = read_data(csv, info)
    runs, scoring = [(data, {**data.start_values, "cycle": 1})], Scoring("rk4", 0.01)
    ranked, fits = calibrate(fmu, info, runs, scoring)
    leading = [s.name for s in ranked[:2]]
    products = ({"drag_coefficient", "frontal_area", "air_density"}, {"rolling_coefficient", "gravity"})
    assert any(set(leading) <= factors for factors in products)
    # of the twins the one declared first is fitted, however round-off ranked them
    first, twin = sorted(ranked[:2], key=lambda s: s.declared_at)
    assert [v.name for v in info.parameters].index(first.name) < [v.name for v in info.parameters].index(twin.name)
    assert first.equivalent == [twin.name]
    assert [f.name for f in fits] == [first.name]          # the twin is neither fitted nor scored
    assert fits[0].details(ranked, "vldm.csv")["equivalent_parameters"] == [twin.name]
    # the reference: fitted on its own the twin reaches the same training score
    alone = fit_parameter(fmu, runs, scoring, twin.name, twin.declared)
    assert alone.train_score == pytest.approx(fits[0].train_score, rel=1e-3)


@pytest.mark.parametrize("later_ranked_first", [True, False])
def test_of_twins_the_first_declared_is_kept_whatever_their_rank(later_ranked_first):
    direction = np.array([1.0, -2.0, 0.5])
    early = Sensitivity("rolling_coefficient", 0.01, 0.5, direction, declared_at=3)
    late = Sensitivity("gravity", 9.81, 0.5 + (1e-15 if later_ranked_first else -1e-15),
                       direction * (1 + 1e-9), declared_at=7)
    other = Sensitivity("mass", 1000.0, 0.4, np.array([0.0, 1.0, 1.0]), declared_at=5)
    ranked = sorted([early, late, other], key=lambda s: s.explained, reverse=True)
    kept = distinct(ranked)
    assert [s.name for s in kept] == ["rolling_coefficient", "mass"]
    assert kept[0].equivalent == ["gravity"] and late.equivalent == []


def test_only_free_real_parameters_are_calibrated():
    info = read_model_info(example_fmu("vldm"))
    names = {v.name for v in calibratable_parameters(info, {"mass"})}
    assert "mass" not in names                       # set by the data's start values
    assert "slope" not in names                      # start 0: no scale to perturb by
    assert "cycle" not in names                      # an Integer
    assert {"rolling_coefficient", "drag_coefficient"} <= names


# ---------------------------------------------------------------------------------------
# the export: an FMU that applies the calibrated value itself


def export_calibrated(original, parameters, output, force=False):
    return export_hybrid(HybridSpec.calibration(original, parameters), output, force=force)


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    return export_calibrated(example_fmu("sampled_plant"), {"b": TRUE_FRICTION},
                             tmp_path_factory.mktemp("calibrated") / "plant_calibrated.fmu")


def test_the_calibrated_hybrid_reproduces_the_original_with_the_value_in_fmpy(calibrated):
    original = example_fmu("sampled_plant")
    assert validate_fmu(str(calibrated)) == []
    kwargs = dict(stop_time=3.0, output=["w", "i", "u", "b"], relative_tolerance=1e-8, output_interval=0.01)
    mine = simulate_fmu(str(calibrated), **kwargs)                       # no start values
    reference = simulate_fmu(str(original), start_values={"b": TRUE_FRICTION}, **kwargs)
    declared = simulate_fmu(str(original), **kwargs)
    for name in ("w", "i", "u", "b"):
        np.testing.assert_allclose(mine[name], reference[name], rtol=1e-12, atol=1e-14)
    assert np.max(np.abs(declared["w"] - reference["w"])) > 0.05        # the value matters
    description = read_model_description(str(calibrated))
    start = {v.name: v.start for v in description.modelVariables}
    assert float(start["b"]) == TRUE_FRICTION
    assert description.modelExchange.modelIdentifier == "sampled_plant_hybrid"


def test_a_reset_returns_to_the_calibrated_value(calibrated, tmp_path):
    from fmpy import extract
    description = read_model_description(str(calibrated))
    b = next(v.valueReference for v in description.modelVariables if v.name == "b")
    unzipped = extract(str(calibrated), str(tmp_path / "x"))
    fmu = FMU2Model(guid=description.guid, unzipDirectory=unzipped,
                    modelIdentifier=description.modelExchange.modelIdentifier, instanceName="plant")
    fmu.instantiate()
    try:
        fmu.setReal([b], [0.7])                 # an importer may still set it
        fmu.setupExperiment(startTime=0.0)
        fmu.enterInitializationMode()
        assert fmu.getReal([b]) == [0.7]
        fmu.reset()
        fmu.setupExperiment(startTime=0.0)
        fmu.enterInitializationMode()
        assert fmu.getReal([b]) == [TRUE_FRICTION]
    finally:
        fmu.freeInstance()


def test_the_fmu_state_of_a_hybrid_without_channels_round_trips(calibrated, tmp_path):
    """No gates to keep: the state is the original's, also through its serialization."""
    from fmpy import extract
    description = read_model_description(str(calibrated))
    fmu = FMU2Model(guid=description.guid, unzipDirectory=extract(str(calibrated), str(tmp_path / "x")),
                    modelIdentifier=description.modelExchange.modelIdentifier, instanceName="plant")
    n = description.numberOfContinuousStates
    x = (ctypes.c_double * n)()
    fmu.instantiate()
    try:
        fmu.setupExperiment(startTime=0.0)
        fmu.enterInitializationMode()
        fmu.exitInitializationMode()
        fmu.enterContinuousTimeMode()
        fmu.getContinuousStates(x, n)
        before = list(x)
        state = fmu.deSerializeFMUstate(fmu.serializeFMUstate(fmu.getFMUstate()))
        x[0] += 1.0
        fmu.setContinuousStates(x, n)
        fmu.setFMUstate(state)
        fmu.getContinuousStates(x, n)
        assert list(x) == before
        fmu.freeFMUstate(state)
    finally:
        fmu.freeInstance()


def test_the_calibrated_hybrid_runs_in_the_engine(calibrated):
    ours = simulate(calibrated, stop_time=2.0, solver="euler", step_size=0.001, variables=["w"])
    reference = simulate(example_fmu("sampled_plant"), stop_time=2.0, solver="euler", step_size=0.001,
                         start_values={"b": TRUE_FRICTION}, variables=["w"])
    np.testing.assert_array_equal(ours["w"], reference["w"])


@pytest.mark.parametrize("parameters, message", [
    ({"no_such": 1.0}, "no_such"),
    ({"w": 1.0}, "only a Real parameter"),
    ({"b": float("nan")}, "finite"),
    ({}, "neither channels nor overrides"),
])
def test_bad_calibrations_are_one_clear_error(parameters, message, tmp_path):
    with pytest.raises(FmuBuilderError, match=message):
        export_calibrated(example_fmu("sampled_plant"), parameters, tmp_path / "out.fmu")
    assert not (tmp_path / "out.fmu").exists()


def test_an_existing_output_needs_force(calibrated):
    with pytest.raises(FmuBuilderError, match="exists"):
        export_calibrated(example_fmu("sampled_plant"), {"b": 0.1}, calibrated)


# ---------------------------------------------------------------------------------------
# the workflow: calibration is a candidate, chosen on the validation data like the others


def test_hybridize_chooses_and_publishes_the_calibration_when_it_is_best_on_validation(plant_files, tmp_path):
    train, test = plant_files
    result = hybridize(example_fmu("sampled_plant"), train, test, tmp_path / "out.fmu", tmp_path / "report",
                       budget=1, ann_on_term=False, progress=False)
    report = result.report
    scores = report["selection"]["scores"]
    assert "calibrated b" in scores and "neural" in scores
    assert report["chosen"] == "calibrated b" == min(scores, key=scores.get)
    assert report["roundtrip"]["passed"]
    start = {v.name: v.start for v in read_model_description(str(result.hybrid_fmu)).modelVariables}
    assert float(start["b"]) == pytest.approx(TRUE_FRICTION, rel=0.01)
    chosen = next(m for m in report["models"] if m["chosen"])
    assert chosen["calibrated"]["b"] == pytest.approx(TRUE_FRICTION, rel=0.01)
    assert chosen["test_relative_mse"] < 0.01


def test_a_calibration_of_an_fmu_without_fmu_state_functions(tmp_path):
    """canGetAndSetFMUstate="false" and a binary that refuses the calls: the wrapper looks none up."""
    original = example_fmu("sampled_plant_no_fmu_state")
    calibrated = export_calibrated(original, {"b": TRUE_FRICTION}, tmp_path / "plant_calibrated.fmu")
    assert validate_fmu(str(calibrated)) == []
    kwargs = dict(fmi_type="ModelExchange", solver="CVode", stop_time=3.0, output=["w"], relative_tolerance=1e-8,
                  output_interval=0.01)
    mine = simulate_fmu(str(calibrated), **kwargs)
    reference = simulate_fmu(str(original), start_values={"b": TRUE_FRICTION}, **kwargs)
    np.testing.assert_allclose(mine["w"], reference["w"], rtol=1e-12, atol=1e-14)
    assert read_model_description(str(calibrated)).modelExchange.canGetAndSetFMUstate is False
