"""The VLDM example FMU (examples/vldm) and its two truth variants, simulated with fmpy.

References: fmpy's validator and simulator, the driving-cycle CSV files the model tables are
generated from, the road-load work computed from the simulated speed with the declared
parameters, and fmpy's own forward-Euler run for the hand-written stepping loop.
"""

import ctypes

import numpy as np
import pytest
from fmpy import extract, instantiate_fmu, read_model_description, simulate_fmu
from fmpy.fmi1 import FMICallException
from fmpy.validation import validate_fmu

from fmubuilder.build import example_fmu, repo_root

VARIANTS = ["vldm", "vldm_truth_extra_resistance", "vldm_truth_extra_loss"]
CYCLE_FILES = {  # value of the parameter `cycle` -> file in examples/vldm/data/cycles
    1: "CADC_Road_100Hz.csv",
    2: "WLTP_class_2_1Hz.csv",
    3: "WLTP_class_3_1Hz.csv",
    4: "EUROPE_ARTEMIS_URBAN_1Hz.csv",
    5: "EUROPE_ARTEMIS_ROAD_1Hz.csv",
    6: "EUROPE_ARTEMIS_MOTORWAY_130_1Hz.csv",
    7: "EUROPE_NEDC_1Hz.csv",
    8: "USA_FTP_75_1Hz.csv",
    9: "USA_FTP_HIGHWAY_1Hz.csv",
    10: "USA_SFTP_US06_1Hz.csv",
    11: "JAPAN_10_15_MODE_1Hz.csv",
}
# Declared parameters (examples/vldm/modelDescription.xml start values).
MASS, MASS_FACTOR, CR, G = 988.5, 1.022, 0.0185, 9.8
AIR = 0.5 * 1.2041 * 0.37 * 1.947  # 0.5 * rho * cd * A
WINDOW = 200.0  # [s] of the CADC road cycle: start, urban driving, two stops

SIGNALS = ["speed", "target_speed", "position", "cycle_position", "energy", "power", "acceleration",
           "driver.throttle", "driver.brake", "drive_force", "standstill"]


def cycle_profile(number):
    """(time, target speed) of a cycle straight from its CSV file."""
    path = repo_root() / "examples" / "vldm" / "data" / "cycles" / CYCLE_FILES[number]
    data = np.genfromtxt(path, delimiter=",", skip_header=1)
    return data[:, 0], data[:, 1]


def simulate(name, solver="CVode", stop_time=WINDOW, **kwargs):
    options = dict(solver=solver, stop_time=stop_time, output=SIGNALS, record_events=False)
    if solver == "Euler":
        options.update(step_size=0.01, output_interval=0.01)
    else:
        options.update(output_interval=0.05)
    options.update(kwargs)
    return simulate_fmu(str(example_fmu(name)), **options)


@pytest.fixture(scope="module")
def declared():
    return simulate("vldm")


@pytest.fixture(scope="module")
def declared_euler():
    return simulate("vldm", solver="Euler")


# ---------------------------------------------------------------------------------------
# interface


@pytest.mark.parametrize("name", VARIANTS)
def test_fmu_is_valid_for_fmpy(name):
    assert validate_fmu(str(example_fmu(name))) == []


def test_truth_variants_share_the_declared_interface():
    declared_xml = read_model_description(str(example_fmu("vldm")))
    for name in VARIANTS[1:]:
        truth = read_model_description(str(example_fmu(name)))
        assert truth.guid == declared_xml.guid
        assert truth.modelExchange.modelIdentifier == "vldm"
        assert [v.name for v in truth.modelVariables] == [v.name for v in declared_xml.modelVariables]


def test_model_description_declares_six_states_and_state_support():
    md = read_model_description(str(example_fmu("vldm")))
    states = [d.variable.derivative.name for d in md.derivatives]
    assert states == ["driver.throttle_integrator", "driver.brake_integrator", "cycle_position",
                      "position", "speed", "energy"]
    assert md.modelExchange.canGetAndSetFMUstate and md.modelExchange.canSerializeFMUstate
    assert not md.modelExchange.providesDirectionalDerivative
    assert {"speed", "acceleration", "power", "energy", "position"} <= {o.variable.name for o in md.outputs}


@pytest.mark.parametrize("start_values", [{"cycle": 0}, {"cycle": 12}, {"mass": -1.0}])
def test_invalid_parameters_are_refused(start_values, tmp_path):
    # extracted here: fmpy leaves its own extraction behind when the run raises
    unzipped = extract(str(example_fmu("vldm")), unzipdir=tmp_path / "vldm")
    with pytest.raises(FMICallException):
        simulate_fmu(unzipped, stop_time=1.0, start_values=start_values, output=SIGNALS)


# ---------------------------------------------------------------------------------------
# behaviour of the declared model


def test_target_speed_is_the_cadc_profile(declared):
    t, v = cycle_profile(1)
    assert np.allclose(declared["target_speed"], np.interp(declared["time"], t, v), rtol=0, atol=1e-9)
    distance = np.trapezoid(np.where(t <= WINDOW, v, 0.0), t)
    assert declared["cycle_position"][-1] == pytest.approx(distance, rel=1e-4)


@pytest.mark.parametrize("number", sorted(CYCLE_FILES))
def test_cycle_parameter_selects_the_profile(number):
    t, v = cycle_profile(number)
    result = simulate("vldm", solver="Euler", stop_time=60.0, start_values={"cycle": number},
                      output=["target_speed"])
    assert np.allclose(result["target_speed"], np.interp(result["time"], t, v), rtol=0, atol=1e-9)


def test_target_is_zero_after_the_cycle_ends():
    t, _ = cycle_profile(10)  # US06, 600 s
    result = simulate("vldm", solver="Euler", start_time=t[-1] - 5.0, stop_time=t[-1] + 5.0,
                      start_values={"cycle": 10}, output=["target_speed", "speed"])
    after = result["time"] > t[-1]
    assert np.all(result["target_speed"][after] == 0.0)
    assert np.all(result["speed"] == 0.0)


@pytest.mark.parametrize("solver", ["CVode", "Euler"])
def test_speed_follows_the_cycle(solver, declared, declared_euler):
    result = declared if solver == "CVode" else declared_euler
    error = result["target_speed"] - result["speed"]
    assert np.sqrt(np.mean(error**2)) < 0.05  # [m/s]
    assert np.max(np.abs(error)) < 0.3
    assert result["speed"].min() >= 0.0
    assert result["position"][-1] == pytest.approx(result["cycle_position"][-1], abs=2.0)


def test_pedals_are_exclusive_and_limited(declared):
    throttle, brake = declared["driver.throttle"], declared["driver.brake"]
    assert throttle.min() >= 0.0 and throttle.max() <= 1.0
    assert brake.min() >= 0.0 and brake.max() <= 1.0
    assert not np.any((throttle > 0) & (brake > 0))
    assert throttle.max() > 0.3 and brake.max() > 0.1  # both controllers act in the window


def test_car_stops_and_restarts(declared):
    standing = declared["standstill"].astype(bool)
    assert standing[0] and np.all(declared["speed"][standing] == 0.0)
    starts = np.count_nonzero(standing[:-1] & ~standing[1:])
    assert starts >= 2


def test_car_does_not_roll_back_on_a_hill():
    # The cycle target is 0 for the first 5 s and no brake is applied: only the standstill
    # logic holds the car on a 10 % gradient.
    result = simulate("vldm", stop_time=4.9, start_values={"slope": 0.1})
    assert np.all(result["speed"] == 0.0) and np.all(result["position"] == 0.0)


def test_energy_covers_the_traction_work(declared):
    """Traction work from the speed trace (finite differences, declared road loads) agrees
    with the model's drive force and is a plausible share of the electrical energy."""
    t, v = declared["time"], declared["speed"]
    road_load = CR * MASS * G * (v > 0) + AIR * v**2
    traction = np.maximum(MASS * MASS_FACTOR * np.gradient(v, t) + road_load, 0.0) * v
    traction_work = np.trapezoid(traction, t)
    assert traction_work == pytest.approx(np.trapezoid(declared["drive_force"] * v, t), rel=0.01)

    energy = declared["energy"][-1]
    assert np.all(np.diff(declared["energy"]) >= 0.0)  # this car has no recuperation
    assert energy == pytest.approx(np.trapezoid(declared["power"], t), rel=5e-3)  # power jumps at ticks
    assert 0.6 < traction_work / energy < 0.95  # motor, power electronics, auxiliaries
    consumption = energy / 3.6e6 / (declared["position"][-1] / 1e5)  # [kWh/100 km]
    assert 8.0 < consumption < 30.0


# ---------------------------------------------------------------------------------------
# truth variants


def test_extra_resistance_raises_energy_while_tracking(declared_euler):
    truth = simulate("vldm_truth_extra_resistance", solver="Euler")
    error = truth["target_speed"] - truth["speed"]
    assert np.sqrt(np.mean(error**2)) < 0.05
    assert 1.03 < truth["energy"][-1] / declared_euler["energy"][-1] < 1.20
    # The driver needs more drive force for the same speed.
    driving = declared_euler["speed"] > 5.0
    assert np.mean(truth["drive_force"][driving]) > np.mean(declared_euler["drive_force"][driving])


def test_extra_loss_raises_energy_only(declared_euler):
    truth = simulate("vldm_truth_extra_loss", solver="Euler")
    assert np.array_equal(truth["speed"], declared_euler["speed"])
    assert np.array_equal(truth["position"], declared_euler["position"])
    assert 1.03 < truth["energy"][-1] / declared_euler["energy"][-1] < 1.15


# ---------------------------------------------------------------------------------------
# FMU state


class EulerLoop:
    """Forward Euler at the 0.01 s controller period: every step ends at a time event, so
    event mode after each step also catches the state events (like fmpy's Euler)."""

    STEP = 0.01

    def __init__(self, tmp_path):
        fmu = str(example_fmu("vldm"))
        self.md = read_model_description(fmu)
        unzipdir = extract(fmu, unzipdir=tmp_path / "vldm")
        self.fmu = instantiate_fmu(unzipdir, self.md, fmi_type="ModelExchange")
        self.fmu.setupExperiment(startTime=0.0)
        self.fmu.enterInitializationMode()
        self.fmu.exitInitializationMode()
        self.event_update()
        self.fmu.enterContinuousTimeMode()
        self.time = 0.0
        self.vr = {v.name: v.valueReference for v in self.md.modelVariables}

    def event_update(self):
        while self.fmu.newDiscreteStates()[0]:
            pass

    def run(self, steps):
        """Speed and energy after each step."""
        nx = self.md.numberOfContinuousStates
        x, dx = np.zeros(nx), np.zeros(nx)
        px, pdx = (a.ctypes.data_as(ctypes.POINTER(ctypes.c_double)) for a in (x, dx))
        trace = []
        for _ in range(steps):
            self.fmu.getContinuousStates(px, nx)
            self.fmu.getDerivatives(pdx, nx)
            x += self.STEP * dx
            self.time += self.STEP
            self.fmu.setTime(self.time)
            self.fmu.setContinuousStates(px, nx)
            self.fmu.enterEventMode()
            self.event_update()
            self.fmu.enterContinuousTimeMode()
            trace.append(self.fmu.getReal([self.vr["speed"], self.vr["energy"]]))
        return np.array(trace)


def test_fmu_state_round_trip_reproduces_the_continuation(tmp_path):
    loop = EulerLoop(tmp_path)
    loop.run(3000)  # 30 s: the car is driving
    state = loop.fmu.getFMUState()
    serialized = loop.fmu.serializeFMUState(state)
    saved_time = loop.time
    reference = loop.run(1000)

    loop.fmu.setFMUState(state)
    loop.time = saved_time
    assert np.array_equal(loop.run(1000), reference)

    restored = loop.fmu.deserializeFMUState(serialized)
    loop.fmu.setFMUState(restored)
    loop.time = saved_time
    assert np.array_equal(loop.run(1000), reference)
    loop.fmu.freeFMUState(restored)
    loop.fmu.freeFMUState(state)

    # The hand-written loop agrees with fmpy's Euler, so the trajectory is a real simulation.
    fmpy_run = simulate("vldm", solver="Euler", stop_time=40.0, output=["speed", "energy"])
    assert reference[-1] == pytest.approx([fmpy_run["speed"][-1], fmpy_run["energy"][-1]], rel=1e-9)
    loop.fmu.terminate()
    loop.fmu.freeInstance()
