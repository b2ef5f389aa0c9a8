"""The example FMUs (examples/) and the FMI 2.0 glue, checked against fmpy and hand-derived answers.

References: fmpy's validator and simulator, closed-form trajectories of the models, the exact
zero-order-hold discretization of the sampled plant (scipy), and finite differences.
"""

import ctypes
import math
import shutil
import subprocess

import numpy as np
import pytest
from fmpy import extract, read_model_description, simulate_fmu
from fmpy.fmi1 import FMICallException
from fmpy.fmi2 import (
    FMU2Model,
    fmi2CallbackAllocateMemoryTYPE,
    fmi2CallbackFreeMemoryTYPE,
    fmi2CallbackFunctions,
    fmi2CallbackLoggerTYPE,
    fmi2CoSimulation,
    fmi2Error,
    fmi2EventInfo,
    fmi2ModelExchange,
)
from fmpy.validation import validate_fmu
from scipy.linalg import expm

from fmubuilder.build import example_fmu, list_examples
from fmubuilder.errors import FmuBuilderError

OWN_EXAMPLES = ["bouncing_ball", "sampled_plant", "event_corner_cases"]

# bouncing_ball value references (examples/bouncing_ball/config.h)
H, DER_H, V, DER_V, G, E, V_MIN, BOUNCES = range(8)


# ---------------------------------------------------------------------------------------
# helpers


class LowLevelFmu:
    """One fmpy FMU2Model instance with a logger that records (status, message)."""

    def __init__(self, fmu_path, tmp_path, name="instance"):
        self.description = read_model_description(fmu_path)
        # Instances of one FMU share the unzipped folder, hence one loaded shared library.
        self.unzipdir = tmp_path / self.description.modelExchange.modelIdentifier
        if not self.unzipdir.is_dir():
            extract(fmu_path, unzipdir=self.unzipdir)
        self.messages = []
        self.callbacks = _recording_callbacks(self.messages)
        self.model = FMU2Model(
            guid=self.description.guid,
            unzipDirectory=self.unzipdir,
            modelIdentifier=self.description.modelExchange.modelIdentifier,
            instanceName=name,
        )
        self.model.instantiate(callbacks=self.callbacks)

    def vr(self, name):
        return next(v.valueReference for v in self.description.modelVariables if v.name == name)

    def initialize(self, start_values=None):
        self.model.setupExperiment(startTime=0.0)
        self.model.enterInitializationMode()
        for vr, value in (start_values or {}).items():
            self.model.setReal([vr], [value])
        self.model.exitInitializationMode()
        info = self.model.newDiscreteStates()
        while info[0]:  # newDiscreteStatesNeeded
            info = self.model.newDiscreteStates()
        self.model.enterContinuousTimeMode()

    def states(self):
        nx = self.description.numberOfContinuousStates
        x = np.zeros(nx)
        self.model.getContinuousStates(x.ctypes.data_as(ctypes.POINTER(ctypes.c_double)), nx)
        return x

    def set_states(self, x):
        x = np.ascontiguousarray(x, dtype=float)
        self.model.setContinuousStates(x.ctypes.data_as(ctypes.POINTER(ctypes.c_double)), x.size)

    def derivatives(self):
        nx = self.description.numberOfContinuousStates
        dx = np.zeros(nx)
        self.model.getDerivatives(dx.ctypes.data_as(ctypes.POINTER(ctypes.c_double)), nx)
        return dx

    def event_indicators(self):
        nz = self.description.numberOfEventIndicators
        z = np.zeros(nz)
        self.model.getEventIndicators(z.ctypes.data_as(ctypes.POINTER(ctypes.c_double)), nz)
        return z

    def errors(self):
        return [message for status, message in self.messages if status == fmi2Error]

    def close(self):
        self.model.freeInstance()


def _recording_callbacks(messages):
    from fmpy import calloc, free

    # fmpy's addLoggerProxy keeps the last logger in a process-wide variable, which would
    # dangle once these callbacks are collected. The glue passes preformatted text with
    # '%' doubled, so the message needs no C-side formatting.
    def logger(env, instance, status, category, message):
        messages.append((status, message.decode().replace("%%", "%")))

    callbacks = fmi2CallbackFunctions()
    callbacks.logger = fmi2CallbackLoggerTYPE(logger)
    callbacks.allocateMemory = fmi2CallbackAllocateMemoryTYPE(calloc)
    callbacks.freeMemory = fmi2CallbackFreeMemoryTYPE(free)
    return callbacks


@pytest.fixture
def ball(tmp_path):
    fmu = LowLevelFmu(example_fmu("bouncing_ball"), tmp_path)
    yield fmu
    fmu.close()


def bouncing_ball_schedule(h0, g, e, v_min):
    """Impact times and the number of impacts until the ball rests, from the closed form."""
    v_impact = math.sqrt(2 * g * h0)
    times = [math.sqrt(2 * h0 / g)]
    while e * v_impact >= v_min:
        v_impact *= e  # rebound speed = next impact speed
        times.append(times[-1] + 2 * v_impact / g)
    return times


def simulate(name, solver, **kwargs):
    # fmpy's Euler takes one step per output interval, so the interval is the step size.
    interval = 1e-3 if solver == "Euler" else 0.01
    options = dict(solver=solver, output_interval=interval, step_size=interval if solver == "Euler" else None)
    options.update(kwargs)
    return simulate_fmu(str(example_fmu(name)), **options)


def first_time(result, name, at_least):
    index = np.argmax(result[name] >= at_least)
    assert result[name][index] >= at_least, f"{name} never reached {at_least}"
    return result["time"][index]


# ---------------------------------------------------------------------------------------
# building and validation


def test_list_examples_names_the_declared_models():
    assert set(OWN_EXAMPLES) <= set(list_examples())


def test_unknown_example_is_a_user_error():
    with pytest.raises(FmuBuilderError, match="unknown example FMU 'no_such_model'"):
        example_fmu("no_such_model")


@pytest.mark.parametrize("name", OWN_EXAMPLES)
def test_example_is_valid_for_fmpy(name):
    assert validate_fmu(str(example_fmu(name))) == []


@pytest.mark.parametrize("name", OWN_EXAMPLES)
def test_example_exports_only_fmi2_functions(name, tmp_path):
    nm = shutil.which("nm")
    if nm is None:
        pytest.skip("nm (binutils) is not installed")
    extract(str(example_fmu(name)), unzipdir=tmp_path)
    library = tmp_path / "binaries" / "linux64" / f"{name}.so"
    symbols = subprocess.run([nm, "-D", "--defined-only", str(library)], capture_output=True, text=True, check=True)
    names = [line.split()[-1] for line in symbols.stdout.splitlines() if line.split()[1] in "TDBR"]
    assert [n for n in names if not n.startswith("fmi2")] == []
    assert {"fmi2Instantiate", "fmi2GetDerivatives", "fmi2NewDiscreteStates"} <= set(names)


# ---------------------------------------------------------------------------------------
# simulation against closed-form answers


@pytest.mark.parametrize("solver, tolerance", [("CVode", 1e-6), ("Euler", 2e-3)])
def test_bouncing_ball_impacts_match_closed_form(solver, tolerance):
    h0, g, e, v_min = 1.5, 9.81, 0.7, 0.1
    result = simulate("bouncing_ball", solver, stop_time=4.0, start_values={"h": h0}, output=["h", "v", "bounces"])
    expected = bouncing_ball_schedule(h0, g, e, v_min)

    assert first_time(result, "bounces", 1) == pytest.approx(math.sqrt(2 * h0 / g), abs=tolerance)
    assert first_time(result, "bounces", 2) == pytest.approx(expected[1], abs=5 * tolerance)
    assert result["h"].min() > -10 * tolerance  # the ball never sinks into the ground
    if solver == "CVode":
        assert result["bounces"][-1] == len(expected)
        resting = result["time"] > expected[-1] + 1e-3
        assert np.all(result["h"][resting] == 0.0) and np.all(result["v"][resting] == 0.0)


def zoh_speed_reference(setpoint, n_samples, R=1.0, L=0.05, K=0.5, J=0.1, b=0.05, Kp=0.5, Ki=2.0, Ts=0.01):
    """Motor speed at the sample instants, from the exact discretization of the plant."""
    A = np.array([[-R / L, -K / L], [K / J, -b / J]])
    B = np.array([[1 / L], [0.0]])
    augmented = expm(np.block([[A, B], [np.zeros((1, 3))]]) * Ts)
    Ad, Bd = augmented[:2, :2], augmented[:2, 2]
    x, integral, speeds = np.zeros(2), 0.0, [0.0]
    for _ in range(n_samples):
        error = setpoint - x[1]
        integral += Ki * Ts * error
        x = Ad @ x + Bd * (Kp * error + integral)
        speeds.append(x[1])
    return np.array(speeds)


@pytest.mark.parametrize("solver, tolerance", [("CVode", 1e-4), ("Euler", 1e-2)])
def test_sampled_plant_follows_zero_order_hold_reference(solver, tolerance):
    setpoint, stop_time = 1.5, 3.0
    result = simulate(
        "sampled_plant", solver, stop_time=stop_time, record_events=False,
        start_values={"setpoint": setpoint}, output=["w", "u", "samples"],
    )
    reference = zoh_speed_reference(setpoint, n_samples=300)
    sample_times = np.arange(301) * 0.01
    speed = np.interp(sample_times, result["time"], result["w"])
    assert np.allclose(speed, reference, rtol=tolerance, atol=tolerance * setpoint)
    assert result["w"][-1] == pytest.approx(setpoint, rel=1e-3)  # integral action: no offset
    assert result["samples"][-1] == 301  # t = 0, 0.01, ..., 3.0


def test_sampled_plant_tracks_a_setpoint_input_change():
    signal = np.array([(0.0, 1.0), (1.005, 1.0), (1.005, 2.0), (4.0, 2.0)], dtype=[("time", float), ("setpoint", float)])
    result = simulate("sampled_plant", "CVode", stop_time=4.0, input=signal, output=["w"])
    before_change = result["time"] <= 1.0
    assert result["w"][before_change][-1] == pytest.approx(1.0, abs=0.01)
    assert result["w"][-1] == pytest.approx(2.0, rel=1e-3)


@pytest.mark.parametrize("solver", ["CVode", "Euler"])
def test_event_corner_cases_happen_when_computed_by_hand(solver):
    t_step, t_terminate = 0.5, 3.5
    result = simulate("event_corner_cases", solver, stop_time=5.0)
    first = result[0]
    last = result[-1]

    # 1: the time event at the start time is handled in the initial event iteration (2 passes)
    assert (first["start_ticks"], first["start_ticks_seen"]) == (1, 1)
    # 2 + 3: both indicators cross at t = 1, 2, 3 and each crossing resets p once
    for k in (1, 2, 3):
        assert first_time(result, "resets", k) == pytest.approx(float(k), abs=1e-6)
    # 4: the step event lands on the first integrator step end at or after t_step
    assert t_step - 1e-9 <= last["step_event_time"] <= t_step + 0.01 + 1e-9
    t_s = last["step_event_time"]
    # 5: termination requested at t_terminate ends the run before stop_time
    assert last["time"] == pytest.approx(t_terminate, abs=1e-9)
    assert last["resets"] == 3
    assert last["p"] == pytest.approx(t_terminate - 3.0, abs=1e-6)
    assert last["r"] == pytest.approx(2 * t_s - t_terminate, abs=1e-6)


def test_event_corner_cases_with_shifted_start_time():
    result = simulate("event_corner_cases", "CVode", start_time=0.25, stop_time=5.0, start_values={"t_terminate": 2.75})
    assert (result[0]["start_ticks"], result[0]["start_ticks_seen"]) == (1, 1)
    assert first_time(result, "resets", 1) == pytest.approx(1.25, abs=1e-6)
    assert first_time(result, "resets", 2) == pytest.approx(2.25, abs=1e-6)
    assert result[-1]["time"] == pytest.approx(2.75, abs=1e-9)


# ---------------------------------------------------------------------------------------
# the FMI 2.0 glue, called directly


def euler_until_first_impact(instances, dt=1e-4):
    """Integrate several instances in lock step; return each one's first impact time."""
    impact = [None] * len(instances)
    t = 0.0
    while any(time is None for time in impact):
        t += dt
        for i, fmu in enumerate(instances):
            if impact[i] is None:
                fmu.model.setTime(t)
                fmu.set_states(fmu.states() + dt * fmu.derivatives())
                if fmu.event_indicators()[0] <= 0:
                    impact[i] = t
    return impact


def test_two_instances_in_one_process_are_independent(tmp_path):
    fmu_path = example_fmu("bouncing_ball")
    a = LowLevelFmu(fmu_path, tmp_path, name="a")
    b = LowLevelFmu(fmu_path, tmp_path, name="b")
    try:
        a.initialize({H: 1.0})
        b.initialize({H: 3.0, G: 3.0})
        t_a, t_b = euler_until_first_impact([a, b])
        assert t_a == pytest.approx(math.sqrt(2 * 1.0 / 9.81), abs=1e-3)
        assert t_b == pytest.approx(math.sqrt(2 * 3.0 / 3.0), abs=1e-3)
        assert a.model.getReal([G]) == [9.81] and b.model.getReal([G]) == [3.0]
    finally:
        a.close()
        b.close()


def bounce(fmu):
    """Drive one impact through event mode; returns the event info tuple."""
    fmu.model.enterEventMode()
    info = fmu.model.newDiscreteStates()
    fmu.model.enterContinuousTimeMode()
    return info


def test_fmu_state_round_trip_restores_states_and_discrete_values(ball):
    ball.initialize()
    ball.model.setTime(0.45)
    ball.set_states([0.01, -4.4])
    saved = ball.model.getFMUstate()

    ball.model.setTime(0.46)
    ball.set_states([-0.03, -4.5])
    info = bounce(ball)
    assert info[3]  # valuesOfContinuousStatesChanged
    assert ball.model.getInteger([BOUNCES]) == [1]
    assert ball.states() == pytest.approx([0.0, 0.7 * 4.5])

    ball.model.setFMUstate(saved)
    assert ball.states().tolist() == [0.01, -4.4]
    assert ball.model.getInteger([BOUNCES]) == [0]
    assert ball.derivatives().tolist() == [-4.4, -9.81]
    ball.model.freeFMUstate(saved)


def test_serialized_state_restores_into_another_instance(ball, tmp_path):
    ball.initialize({E: 0.5})
    ball.model.setTime(0.5)
    ball.set_states([-0.01, -5.0])
    bounce(ball)
    state = ball.model.getFMUstate()
    blob = ball.model.serializeFMUstate(state)
    ball.model.freeFMUstate(state)

    other = LowLevelFmu(example_fmu("bouncing_ball"), tmp_path, name="other")
    try:
        other.initialize()
        restored = other.model.deSerializeFMUstate(blob)
        other.model.setFMUstate(restored)
        other.model.freeFMUstate(restored)
        assert other.states().tolist() == [0.0, 2.5]
        assert other.model.getInteger([BOUNCES]) == [1]
        assert other.model.getReal([E]) == [0.5]
    finally:
        other.close()


def test_deserialization_rejects_foreign_and_damaged_blobs(ball, tmp_path):
    ball.initialize()
    state = ball.model.getFMUstate()
    blob = ball.model.serializeFMUstate(state)
    ball.model.freeFMUstate(state)

    plant = LowLevelFmu(example_fmu("sampled_plant"), tmp_path, name="plant")
    try:
        plant.initialize()
        with pytest.raises(FMICallException):
            plant.model.deSerializeFMUstate(blob)  # another model's state
        assert plant.errors()
    finally:
        plant.close()
    with pytest.raises(FMICallException):
        ball.model.deSerializeFMUstate(blob[:-8])  # truncated
    damaged = bytearray(blob)
    damaged[20] ^= 0xFF  # inside the GUID
    with pytest.raises(FMICallException):
        ball.model.deSerializeFMUstate(bytes(damaged))


def test_wrong_state_calls_return_error_and_leave_the_instance_usable(ball):
    m = ball.model
    with pytest.raises(FMICallException):
        ball.derivatives()  # not initialized yet
    with pytest.raises(FMICallException):
        m.enterContinuousTimeMode()
    with pytest.raises(FMICallException):
        m.newDiscreteStates()
    with pytest.raises(FMICallException):
        m.terminate()
    assert any("fmi2GetDerivatives must not be called in state Instantiated" in e for e in ball.errors())

    ball.initialize()
    with pytest.raises(FMICallException):
        m.setupExperiment(startTime=0.0)
    with pytest.raises(FMICallException):
        m.newDiscreteStates()  # continuous-time mode
    with pytest.raises(FMICallException):
        m.setReal([G], [1.0])  # fixed parameter after initialization
    with pytest.raises(FMICallException):
        m.getReal([99])  # unknown value reference
    assert ball.derivatives().tolist() == [0.0, -9.81]  # still works


def test_bad_arguments_return_error(ball):
    ball.initialize()
    m = ball.model
    two = (ctypes.c_double * 2)()
    with pytest.raises(FMICallException):
        m.fmi2GetEventIndicators(m.component, None, 1)  # NULL array
    with pytest.raises(FMICallException):
        m.fmi2GetContinuousStates(m.component, two, 3)  # nx does not match NX = 2
    with pytest.raises(FMICallException):
        m.fmi2SetContinuousStates(m.component, two, 1)
    with pytest.raises(FMICallException):
        m.fmi2NewDiscreteStates(m.component, None)
    with pytest.raises(FMICallException):
        m.fmi2GetFMUstate(m.component, None)
    info = fmi2EventInfo()
    with pytest.raises(FMICallException):
        m.fmi2NewDiscreteStates(m.component, ctypes.byref(info))  # not in event mode
    assert any("must not be NULL" in e for e in ball.errors())
    assert any("nx is 3 but the model has 2" in e for e in ball.errors())


def test_instantiate_refuses_co_simulation_and_wrong_guid(ball):
    m = ball.model
    name, location = b"x", b"file:///tmp"
    guid = ball.description.guid.encode()
    callbacks = ctypes.byref(ball.callbacks)
    assert m.fmi2Instantiate(name, fmi2CoSimulation, guid, location, callbacks, 0, 0) is None
    assert m.fmi2Instantiate(name, fmi2ModelExchange, b"{wrong}", location, callbacks, 0, 0) is None
    assert any("Co-Simulation" in e for e in ball.errors())
    assert any("does not match" in e for e in ball.errors())


def test_reset_returns_to_start_values(ball):
    ball.initialize({H: 2.0})
    ball.model.reset()
    ball.initialize()
    assert ball.states().tolist() == [1.0, 0.0]


def test_debug_logging_reports_events_only_when_enabled(ball):
    ball.model.setDebugLogging(True, ["logEvents"])
    with pytest.raises(FMICallException):
        ball.model.setDebugLogging(True, ["noSuchCategory"])
    ball.initialize()
    ball.model.setTime(0.45)
    ball.set_states([-0.001, -4.4])
    bounce(ball)
    assert any("impact 1" in message for _, message in ball.messages)


@pytest.mark.parametrize("state", [[0.5, -1.0], [2.0, 3.0]])
def test_bouncing_ball_directional_derivative_matches_finite_differences(ball, state):
    ball.initialize()
    ball.set_states(state)
    step = 1e-6
    jacobian = np.zeros((2, 2))
    for j in range(2):
        plus, minus = np.array(state, float), np.array(state, float)
        plus[j] += step
        minus[j] -= step
        ball.set_states(plus)
        f_plus = ball.derivatives()
        ball.set_states(minus)
        f_minus = ball.derivatives()
        jacobian[:, j] = (f_plus - f_minus) / (2 * step)
    ball.set_states(state)

    seed = [0.3, -1.7]
    directional = ball.model.getDirectionalDerivative([DER_H, DER_V], [H, V], seed)
    assert directional == pytest.approx(jacobian @ seed, abs=1e-8)
    # outputs that are states: identity
    assert ball.model.getDirectionalDerivative([H, V], [H, V], seed) == pytest.approx(seed)


def test_directional_derivative_is_an_error_without_support(tmp_path):
    plant = LowLevelFmu(example_fmu("sampled_plant"), tmp_path, name="plant")
    try:
        plant.initialize()
        with pytest.raises(FMICallException):
            plant.model.getDirectionalDerivative([1], [0], [1.0])
        assert any("does not provide directional derivatives" in e for e in plant.errors())
    finally:
        plant.close()


def test_step_event_is_requested_after_t_step(tmp_path):
    fmu = LowLevelFmu(example_fmu("event_corner_cases"), tmp_path, name="corner")
    try:
        fmu.initialize()
        fmu.model.setTime(0.4)
        assert fmu.model.completedIntegratorStep() == (False, False)
        fmu.model.setTime(0.5)
        assert fmu.model.completedIntegratorStep() == (True, False)
        info = bounce(fmu)
        assert info[4] and info[5] == 3.5  # next time event: the termination request
        assert fmu.model.getReal([fmu.vr("step_event_time")]) == [0.5]
        assert fmu.model.completedIntegratorStep() == (False, False)
    finally:
        fmu.close()


# ---------------------------------------------------------------------------------------
# DC drive truths with effects outside the term library (examples/dc_drive/model.c)

# truth variant -> (derivative its effect enters first, any further derivative it enters)
DC_DRIVE_NEW_EFFECTS = {
    "stribeck": ("der(speed)", None),
    "coulomb": ("der(speed)", None),
    "speed_current_loss": ("der(energy)", None),
    "two_effects": ("der(speed)", "der(energy)"),
}


@pytest.fixture(scope="module")
def dc_drive_training_runs():
    from fmubuilder.examples_zoo import cached_data, dc_drive_data_sets
    sets = [s for s in dc_drive_data_sets() if s.cycle.role == "train"]
    paths, _ = cached_data(sets)
    return {s.variant.key: path for s, path in zip(sets, paths)}


@pytest.mark.parametrize("variant", sorted(DC_DRIVE_NEW_EFFECTS))
def test_dc_drive_new_truths_are_diagnosed_into_their_derivatives(dc_drive_training_runs, variant):
    """Each truth's effect is significant in its data and traced to the derivative it enters (the
    first pass of the profile, 30 s); the two-effect truth names both derivatives, the better one
    as the channel, the other as about as good."""
    from fmubuilder.data import load_data
    from fmubuilder.diagnose import diagnose
    from fmubuilder.fmi import read_model_info
    fmu = example_fmu("dc_drive")
    data = load_data(dc_drive_training_runs[variant], read_model_info(fmu))
    d = diagnose(fmu, data.window(data.start, 30.0))
    first, further = DC_DRIVE_NEW_EFFECTS[variant]
    assert d.significant and d.p_value < 1e-6
    if further is None:
        assert d.channel == first
    else:
        assert {d.channel, *d.ambiguous_channels} >= {first, further}


def test_dc_drive_control_data_show_no_effect(dc_drive_training_runs):
    from fmubuilder.data import load_data
    from fmubuilder.diagnose import diagnose
    from fmubuilder.fmi import read_model_info
    fmu = example_fmu("dc_drive")
    data = load_data(dc_drive_training_runs["no_effect"], read_model_info(fmu))
    assert not diagnose(fmu, data.window(data.start, 30.0)).significant


def test_dc_drive_profile_repeats_drive_the_profile_again():
    """profile_repeats=2: the second 30 s repeat the first (set-point and load); 1 (the default):
    the last breakpoint holds after 30 s, as before the parameter existed."""
    fmu = str(example_fmu("dc_drive"))
    names = ["speed_reference", "load_torque"]
    twice = simulate_fmu(fmu, stop_time=60.0, start_values={"profile_repeats": 2.0}, output=names,
                         output_interval=0.25, record_events=False)
    once = simulate_fmu(fmu, stop_time=60.0, output=names, output_interval=0.25, record_events=False)
    first, second = twice["time"] < 30.0 - 1e-9, twice["time"] >= 30.0 - 1e-9
    for name in names:
        np.testing.assert_allclose(twice[name][second][:first.sum()], twice[name][first], atol=1e-9)
        np.testing.assert_allclose(once[name][first], twice[name][first], atol=1e-12)
        assert np.all(once[name][once["time"] >= 30.0] == once[name][-1])
    assert np.ptp(twice["speed_reference"][second]) == pytest.approx(320.0)   # -120 ... 200 rad/s
