"""diagnose() on data logged from truth FMUs with an effect the declared model lacks.

The truth is known from the C sources (examples/dc_drive/model.c, examples/vldm/model.c):
which derivative each effect enters, which variable it depends on and, for the DC drive, its
coefficient. The declared model's own data are the control: no significant effect.
"""
import math

import pytest

from fmubuilder.build import example_fmu
from fmubuilder.diagnose import diagnose

from .conftest import DC_DRIVE_BENCH, VLDM_BENCH, measure

NO_BUDGET_LIMIT = math.inf     # trace the whole window whatever the machine's speed
DC_DRIVE_WINDOW = 15.0         # s: start-up, load step, braking, speed reversal
VLDM_WINDOW = 30.0             # s of the CADC road cycle: start, acceleration and a braking phase
WINDAGE = 3e-6 / 0.01          # der(speed) += -WINDAGE * speed*|speed|
EXTRA_HEATING = 0.3 / 10.0     # der(temperature) += EXTRA_HEATING * current^2


def _diagnose(model, data, **kwargs):
    return diagnose(example_fmu(model), data, time_budget=NO_BUDGET_LIMIT, **kwargs)


# ---------------------------------------------------------------------------------------
# DC drive


@pytest.fixture(scope="module")
def dc_drive_data(data_dir):
    return {truth: measure(data_dir, truth, stop_time=DC_DRIVE_WINDOW, bench=DC_DRIVE_BENCH)
            for truth in ("dc_drive", "dc_drive_truth_windage", "dc_drive_truth_extra_heating")}


def test_dc_drive_own_data_show_no_significant_effect(dc_drive_data):
    d = _diagnose("dc_drive", dc_drive_data["dc_drive"])
    assert not d.significant
    assert d.channel is None and d.inputs == [] and d.fitted_term is None
    assert d.simulations == 1
    for e in d.errors:
        assert e.rms < 1.3 * e.noise, e


def test_dc_drive_windage_is_traced_to_the_speed_derivative(dc_drive_data):
    d = _diagnose("dc_drive", dc_drive_data["dc_drive_truth_windage"])
    assert d.significant
    errors = {e.signal: e for e in d.errors}
    # Closed loop: the controller holds the speed on its set-point and draws more current.
    assert not errors["speed"].significant
    assert errors["current"].significant and errors["power"].significant
    assert d.channel == "der(speed)" and d.ambiguous_channels == []
    assert d.inputs[0] == "speed"
    term = d.fitted_term
    assert term["offered"]
    assert [(t["variable"], t["basis"]) for t in term["terms"]] == [("speed", "w*|w|")]
    assert term["terms"][0]["coefficient"] == pytest.approx(-WINDAGE, rel=0.05)
    assert term["explained_excess"] > 0.99
    assert errors["current"].corrected_rms < 1.2 * errors["current"].noise   # the rest is noise


def test_dc_drive_extra_heating_is_traced_to_the_temperature_derivative(dc_drive_data):
    d = _diagnose("dc_drive", dc_drive_data["dc_drive_truth_extra_heating"])
    assert d.significant
    assert d.channel == "der(temperature)"
    assert d.inputs[0] == "current"
    term = d.fitted_term
    assert term["offered"]
    assert [(t["variable"], t["basis"]) for t in term["terms"]] == [("current", "w^2")]
    assert term["terms"][0]["coefficient"] == pytest.approx(EXTRA_HEATING, rel=0.05)


def test_an_effect_below_the_noise_of_single_samples_is_found(data_dir):
    """Ten times the sensor noise: the windage residual is about as large as the noise of a
    sample (RMS at most 2.5 times the noise), yet the test finds it and the trace holds."""
    bench = dict(signals=("speed", "current", "power"), noise_std={"speed": 0.5, "current": 0.5, "power": 20.0})
    folder = data_dir / "noisy"
    folder.mkdir()
    d = _diagnose("dc_drive", measure(folder, "dc_drive_truth_windage", stop_time=10.0, bench=bench))
    assert all(e.rms < 2.5 * e.noise for e in d.errors)
    assert d.significant
    assert d.channel == "der(speed)" and d.inputs[0] == "speed"
    control = _diagnose("dc_drive", measure(folder, "dc_drive", stop_time=10.0, bench=bench))
    assert not control.significant


# ---------------------------------------------------------------------------------------
# Coloured sensor noise: real sensors are filtered, their noise correlated between samples

COLOURED_NOISE = {
    "ar1 0.7": dict(noise_model="ar1", noise_rho=0.7),
    "ar1 0.9": dict(noise_model="ar1", noise_rho=0.9),
    "low-pass 0.3 s x2": dict(noise_model="lowpass", noise_filter_tau=0.3, noise_filter_order=2),
    "sensor lag 0.1 s": dict(noise_model="lowpass", noise_filter_tau=0.1),
}


@pytest.mark.parametrize("noise", list(COLOURED_NOISE))
def test_coloured_noise_without_an_effect_is_no_effect(data_dir, noise):
    folder = data_dir / f"coloured_{noise.replace(' ', '_')}"
    folder.mkdir()
    bench = {**DC_DRIVE_BENCH, **COLOURED_NOISE[noise]}
    for seed in range(3):
        d = _diagnose("dc_drive", measure(folder, "dc_drive", stop_time=DC_DRIVE_WINDOW, bench=bench, seed=seed))
        assert not d.significant, (noise, seed, d.p_value)


@pytest.mark.parametrize("noise", ["ar1 0.7", "low-pass 0.3 s x2"])
def test_effects_are_found_in_coloured_noise(data_dir, noise):
    folder = data_dir / f"coloured_effects_{noise.replace(' ', '_')}"
    folder.mkdir()
    bench = {**DC_DRIVE_BENCH, **COLOURED_NOISE[noise]}
    windage = _diagnose("dc_drive", measure(folder, "dc_drive_truth_windage", stop_time=DC_DRIVE_WINDOW, bench=bench))
    assert windage.significant and windage.channel == "der(speed)"
    heating = _diagnose("dc_drive", measure(folder, "dc_drive_truth_extra_heating", stop_time=DC_DRIVE_WINDOW,
                                            bench=bench))
    assert heating.significant and heating.channel == "der(temperature)"


def test_the_time_budget_does_not_change_the_numbers(dc_drive_data):
    """The tracing's work is fixed: a generous budget and none give the same diagnosis; a
    budget too small to finish says that it cut the tracing short."""
    data = dc_drive_data["dc_drive_truth_extra_heating"]
    free = diagnose(example_fmu("dc_drive"), data)
    capped = diagnose(example_fmu("dc_drive"), data, time_budget=1e6)
    assert free.cut_short is None and capped.cut_short is None
    assert capped.p_value == free.p_value and capped.simulations == free.simulations
    assert capped.fitted_term == free.fitted_term and capped.candidates == free.candidates
    assert capped.trace_window == free.window
    tiny = diagnose(example_fmu("dc_drive"), data, time_budget=1e-9)
    assert tiny.p_value == free.p_value and tiny.significant
    assert tiny.cut_short is not None and "time budget" in tiny.cut_short
    assert "Warning: the time budget" in tiny.report()


# ---------------------------------------------------------------------------------------
# VLDM: the electric car on its driving cycle, driven by a sampled PI driver


@pytest.fixture(scope="module")
def vldm_data(data_dir):
    return {truth: measure(data_dir, truth, stop_time=VLDM_WINDOW, bench=VLDM_BENCH, start_values={"cycle": 1})
            for truth in ("vldm", "vldm_truth_extra_resistance", "vldm_truth_extra_loss")}


def test_vldm_own_data_show_no_significant_effect(vldm_data):
    d = _diagnose("vldm", vldm_data["vldm"])
    assert d.start_values == {"cycle": 1}            # taken from the data's sidecar
    assert not d.significant
    assert d.channel is None


def test_vldm_extra_resistance_is_traced_to_the_speed_derivative(vldm_data):
    """The driver compensates the extra driving resistance: the speed stays on the cycle, the
    energy rises, and only the speed derivative explains all signals."""
    d = _diagnose("vldm", vldm_data["vldm_truth_extra_resistance"])
    errors = {e.signal: e for e in d.errors}
    assert d.significant
    assert not errors["speed"].significant and errors["energy"].significant
    assert d.channel == "der(speed)"
    assert d.inputs[0] == "speed"
    assert d.fitted_term["terms"][0]["coefficient"] < 0        # a resistance slows the car


def test_vldm_extra_loss_is_traced_to_the_energy_derivative(vldm_data):
    """An electrical loss proportional to the motor power changes the energy only."""
    d = _diagnose("vldm", vldm_data["vldm_truth_extra_loss"])
    assert d.significant
    assert d.channel == "der(energy)"
    assert d.inputs[0] == "motor_power"
    assert d.fitted_term["terms"][0]["coefficient"] > 0


def test_a_measured_start_that_contradicts_the_model_is_taken_from_the_data(data_dir):
    """Data recorded from a warm motor, without a sidecar naming the start values: the first
    samples give the start temperature; the rest is noise."""
    from fmubuilder.synth import sidecar_path
    folder = data_dir / "warm"
    folder.mkdir()
    bench = {**DC_DRIVE_BENCH, "lag": 0.0}
    path = measure(folder, "dc_drive", stop_time=8.0, bench=bench, start_values={"temperature": 313.15})
    sidecar_path(path).unlink()
    d = _diagnose("dc_drive", path)
    assert set(d.start_values_from_data) == {"temperature"}
    assert d.start_values_from_data["temperature"] == pytest.approx(313.15, abs=0.05)
    assert not d.significant


def test_long_data_are_traced_on_a_fixed_number_of_leading_samples(dc_drive_data, monkeypatch):
    """The tracing's share of the data is a sample count, not a time: the same on any machine."""
    import numpy as np
    from fmubuilder.diagnose import diagnosis as diagnosis_module
    monkeypatch.setattr(diagnosis_module, "TRACE_SAMPLES", 100)
    data = dc_drive_data["dc_drive_truth_extra_heating"]
    stamps = np.loadtxt(data, delimiter=",", skiprows=1, usecols=0)
    d = diagnose(example_fmu("dc_drive"), data)
    assert d.window == (stamps[0], stamps[-1])
    assert d.trace_window == (stamps[0], stamps[99])
    assert d.significant and d.channel == "der(temperature)" and d.cut_short is None
