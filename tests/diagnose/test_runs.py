"""Runs of the declared model with an added term, checked against independent references: the
truth FMUs (the same physics compiled in C and simulated by fmpy), closed-form changes, and the
test bench's own sensor model."""
import fmpy
import numpy as np
import pytest

from fmubuilder import synth
from fmubuilder.build import example_fmu
from fmubuilder.diagnose.diagnosis import derivative_aliases
from fmubuilder.diagnose.runs import TIME, AddedTerm, ModelRunner, form_text
from fmubuilder.diagnose.trace import candidate_variables
from fmubuilder.fmi.archive import read_model_info

from .conftest import DC_DRIVE_BENCH

# Truth variants of examples/dc_drive/model.c, divided by the capacity of their state.
WINDAGE = 3e-6 / 0.01               # [1/rad] per speed*|speed| in der(speed) (windage / inertia)
EXTRA_HEATING = 0.3 / 10.0          # [K/(s.A2)] per current^2 in der(temperature) (resistance / heat capacity)
SIGNALS = ["speed", "current", "power", "temperature"]
STOP = 12.0


def _runner(fmu, times, measured=SIGNALS, sensor_lag=0.0, recorded=()):
    return ModelRunner(fmu, start_values={}, data_time=times, start=0.0, stop=float(times[-1]),
                       measured=measured, recorded=list(recorded), sensor_lag=sensor_lag)


def _fmpy(name, times):
    result = fmpy.simulate_fmu(str(example_fmu(name)), stop_time=float(times[-1]), output=SIGNALS,
                               output_interval=0.01, relative_tolerance=1e-10)
    return {s: np.interp(times, result["time"], result[s]) for s in SIGNALS}


@pytest.mark.parametrize("truth, term", [
    ("dc_drive_truth_windage", AddedTerm(1, "speed", "w*|w|", 0.0, -WINDAGE)),
    ("dc_drive_truth_extra_heating", AddedTerm(3, "current", "w^2", 0.0, EXTRA_HEATING)),
])
def test_declared_model_with_the_missing_term_reproduces_the_truth_fmu(truth, term):
    times = np.linspace(0.0, STOP, 241)
    runner = _runner(example_fmu("dc_drive"), times)
    try:
        with_term = runner.simulate([term]).predicted
        without = runner.simulate().predicted
    finally:
        runner.close()
    reference = _fmpy(truth, times)
    for name in SIGNALS:
        effect = np.max(np.abs(reference[name] - without[name]))
        error = np.max(np.abs(reference[name] - with_term[name]))
        assert effect > 0, name
        assert error <= 2e-4 * effect + 1e-6 * np.max(np.abs(reference[name])), (name, error, effect)


def test_a_term_in_the_energy_derivative_shows_in_the_power_output_too():
    fmu = example_fmu("dc_drive")
    info = read_model_info(fmu)
    times = np.linspace(0.0, 5.0, 101)
    runner = _runner(fmu, times, measured=["power", "energy"], recorded=candidate_variables(info))
    try:
        nominal = runner.simulate()
        runner.output_aliases = derivative_aliases(info, nominal, ["power", "energy"])
        assert runner.output_aliases == {"power": [info.state_index("der(energy)")]}
        constant = 7.5  # W
        shifted = runner.simulate([AddedTerm(4, TIME, "1", 0.0, constant)]).predicted
    finally:
        runner.close()
    # The two runs take different solver steps: agreement to the solver's tolerance.
    energy_scale = np.max(np.abs(nominal.predicted["energy"]))
    power_scale = np.max(np.abs(nominal.predicted["power"]))
    np.testing.assert_allclose(shifted["energy"] - nominal.predicted["energy"], constant * times,
                               atol=1e-5 * energy_scale)
    np.testing.assert_allclose(shifted["power"] - nominal.predicted["power"], constant, atol=1e-5 * power_scale)


def test_model_runs_are_logged_like_the_bench_logs_the_truth(tmp_path):
    """With the bench's sensor lag and time stamps and no noise, the declared model's run must
    give what the bench logs for that same model."""
    settings = synth.BenchSettings(**{**DC_DRIVE_BENCH, "noise_std": {s: 0.0 for s in SIGNALS}}, runs=1)
    fmu = example_fmu("dc_drive")
    logged = synth.measure(fmu, stop_time=STOP, settings=settings)
    runner = _runner(fmu, logged.time, sensor_lag=settings.lag)
    try:
        predicted = runner.simulate().predicted
    finally:
        runner.close()
    for name in SIGNALS:
        scale = np.max(np.abs(logged.true[name][0]))
        np.testing.assert_allclose(predicted[name], logged.true[name][0], atol=2e-5 * scale, err_msg=name)


def test_forms_are_written_around_the_start_value():
    assert form_text("speed", "w*|w|", 0.0) == "speed*|speed|"
    assert form_text("temperature", "w", 293.15) == "(temperature - 293.15)"
    assert form_text("x", "w^2", -2.0) == "(x + 2)^2"
    assert AddedTerm(0, "current", "w^2", 0.0, 0.03).expression() == "0.03 * current^2"


def test_terms_run_in_the_compiled_core_as_in_the_python_loop(monkeypatch):
    """A state's form, an FMU variable's form and a constant on one derivative: the core's base
    term against the Python loop (FMUBUILDER_ENGINE=python), which adds the terms itself."""
    times = np.linspace(0.0, STOP, 241)
    terms = [AddedTerm(1, "speed", "w*|w|", 0.0, -WINDAGE), AddedTerm(1, "current", "w^2", 1.0, 0.02),
             AddedTerm(1, "speed", "1", 0.0, -0.5)]
    runner = _runner(example_fmu("dc_drive"), times)
    try:
        core_run = runner.simulate(terms)
        monkeypatch.setenv("FMUBUILDER_ENGINE", "python")
        python_run = runner.simulate(terms)
    finally:
        runner.close()
    assert core_run.derivative_calls == python_run.derivative_calls
    for name in SIGNALS:
        np.testing.assert_allclose(core_run.predicted[name], python_run.predicted[name], rtol=1e-9,
                                   atol=1e-9 * np.max(np.abs(python_run.predicted[name])))


@pytest.mark.parametrize("engine", ["core", "python"])
def test_a_trial_beyond_its_work_limit_is_abandoned(monkeypatch, engine):
    from fmubuilder.diagnose.runs import TrialTooSlow
    if engine == "python":
        monkeypatch.setenv("FMUBUILDER_ENGINE", "python")
    times = np.linspace(0.0, STOP, 241)
    runner = _runner(example_fmu("dc_drive"), times)
    try:
        calls = runner.simulate([AddedTerm(1, "speed", "w", 0.0, -0.1)]).derivative_calls
        with pytest.raises(TrialTooSlow, match="work limit"):
            runner.simulate([AddedTerm(1, "speed", "w", 0.0, -0.1)], max_calls=calls // 2)
    finally:
        runner.close()
