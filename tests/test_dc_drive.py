"""The DC drive example (examples/dc_drive) against fmpy's validator and relations of its
physics that hold whatever the numbers: steady state of motor and controller, the energy as
the integral of the power, the thermal balance, and truth variants that differ from the
declared model only inside."""
import zipfile

import fmpy
import numpy as np
import pytest
from fmpy.validation import validate_fmu

from fmubuilder.build import example_fmu

VARIANTS = ["dc_drive", "dc_drive_truth_windage", "dc_drive_truth_extra_heating"]
R20, ALPHA, T_REF, K, B = 1.2, 0.00393, 293.15, 0.1, 1e-3     # modelDescription.xml start values
HEAT_CAPACITY, THERMAL_RESISTANCE, T_AMBIENT = 10.0, 2.5, 293.15
OUTPUTS = ["speed", "current", "voltage", "power", "temperature", "energy", "speed_reference",
           "load_torque", "der(temperature)", "der(speed)"]


@pytest.fixture(scope="module")
def run():
    result = fmpy.simulate_fmu(str(example_fmu("dc_drive")), stop_time=30.0, output=OUTPUTS,
                               output_interval=0.005, relative_tolerance=1e-10)
    return {name: np.asarray(result[name]) for name in ["time", *OUTPUTS]}


@pytest.mark.parametrize("name", VARIANTS)
def test_fmpy_validates_every_variant(name):
    assert validate_fmu(str(example_fmu(name))) == []


def test_truth_variants_share_the_declared_model_description():
    declared = zipfile.ZipFile(example_fmu("dc_drive")).read("modelDescription.xml")
    for name in VARIANTS[1:]:
        assert zipfile.ZipFile(example_fmu(name)).read("modelDescription.xml") == declared


def test_the_controller_holds_the_set_point_and_the_motor_carries_the_load(run):
    """On a constant set-point (5.5 s to 6.9 s: 150 rad/s, load 0.5 N.m) the integral action
    removes the speed error, and torque balance gives the current."""
    steady = (run["time"] > 6.5) & (run["time"] < 6.9)
    speed = run["speed"][steady]
    np.testing.assert_allclose(speed, 150.0, atol=0.02)
    np.testing.assert_allclose(run["current"][steady], (B * speed + run["load_torque"][steady]) / K, rtol=1e-3)


def test_voltage_balances_resistance_drop_and_back_emf_in_steady_state(run):
    steady = (run["time"] > 6.5) & (run["time"] < 6.9)
    resistance = R20 * (1 + ALPHA * (run["temperature"][steady] - T_REF))
    expected = resistance * run["current"][steady] + K * run["speed"][steady]
    np.testing.assert_allclose(run["voltage"][steady], expected, rtol=1e-3)


def test_energy_is_the_integral_of_the_power(run):
    from scipy.integrate import cumulative_trapezoid
    integral = cumulative_trapezoid(run["power"], run["time"], initial=0.0)
    np.testing.assert_allclose(run["energy"], integral, atol=1e-4 * run["energy"][-1])


def test_winding_temperature_follows_copper_loss_and_cooling(run):
    resistance = R20 * (1 + ALPHA * (run["temperature"] - T_REF))
    loss = resistance * run["current"] ** 2
    cooling = (run["temperature"] - T_AMBIENT) / THERMAL_RESISTANCE
    np.testing.assert_allclose(run["der(temperature)"], (loss - cooling) / HEAT_CAPACITY, rtol=1e-9, atol=1e-12)


def test_the_set_point_follows_the_profile_and_reverses(run):
    def at(t):
        return float(np.interp(t, run["time"], run["speed_reference"]))
    assert at(1.5) == pytest.approx(75.0)           # ramp 0 -> 150 rad/s over 0.5 s .. 2.5 s
    assert at(13.25) == pytest.approx(-30.0)        # ramp 60 -> -120 rad/s over 12 s .. 14.5 s
    assert at(26.0) == pytest.approx(200.0)
