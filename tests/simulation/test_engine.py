"""The simulation loop: event semantics against closed-form answers, the HybridSystem
protocol with systems written here, fixed-step convergence, and argument errors."""
import math

import numpy as np
import pytest
from scipy.linalg import expm

from fmubuilder.errors import FmuBuilderError
from fmubuilder.fmi import Fmu
from fmubuilder.simulation import DOPRI5, FmuSystem, output_grid, run, simulate

from .reference import fmpy_simulation, rows_at


# ---------------------------------------------------------------------------------------
# event_corner_cases: closed-form answers from the comment in its model.c

def test_corner_cases_against_their_closed_form(example):
    result = simulate(example("event_corner_cases"), rtol=1e-10, atol=1e-10)
    # 1. the time event at t0 is handled in the initial event iteration (two passes)
    assert result["start_ticks"][0] == 1 and result["start_ticks_seen"][0] == 1
    assert result.stats.event_iterations >= 2 + 5
    # 2 + 3. both indicators cross at t = 1, 2, 3 and reset p: one state event each
    state_times = [t for t, kind in result.events if kind == "state"]
    np.testing.assert_allclose(state_times, [1.0, 2.0, 3.0], atol=1e-9)
    assert result.stats.state_events == 3 and result["resets"][-1] == 3
    t = result.time
    away = np.min(np.abs(t[:, None] - np.array([1.0, 2.0, 3.0])), axis=1) > 1e-6
    np.testing.assert_allclose(result["p"][away], np.mod(t[away], 1.0), atol=1e-9)
    # 4. the step event fires at the first step end at or after t_step = 0.5
    t_step = result["step_event_time"][-1]
    assert 0.5 <= t_step <= 0.5 + 5.0 / 50      # default maximum step: (stop - start) / 50
    assert [kind for _, kind in result.events].count("step") == 1
    expected_r = np.where(t < t_step, t, 2 * t_step - t)
    np.testing.assert_allclose(result["r"], expected_r, atol=1e-9)
    # 5. the time event at t_terminate = 3.5 ends the simulation there
    assert result.terminated_early and result.stop_time == 3.5 and result.time[-1] == 3.5
    assert result.stats.time_events == 1
    assert "terminated by the model at t=3.5" in result.stats_line()


@pytest.mark.parametrize("t_terminate, stop_time, resets", [(2.25, 5.0, 2), (7.0, 4.5, 4)])
def test_terminate_simulation_stops_at_the_requested_time(example, t_terminate, stop_time, resets):
    result = simulate(example("event_corner_cases"), stop_time=stop_time,
                      start_values={"t_terminate": str(t_terminate)})
    assert result.terminated_early == (t_terminate < stop_time)
    assert result.time[-1] == min(t_terminate, stop_time)
    assert result["resets"][-1] == resets


def test_fixed_step_solver_steps_onto_the_step_event_like_fmpy(example):
    """RK4 with h = 1 ms ends a step at t_step = 0.5 exactly, as fmpy's output grid does,
    so even the step-dependent variables agree with fmpy (CVode)."""
    path = example("event_corner_cases")
    ours = simulate(path, solver="rk4", step_size=1e-3)
    assert ours["step_event_time"][-1] == 0.5
    theirs, _ = fmpy_simulation(path, output=ours.names, output_interval=1e-3)
    rows = rows_at(theirs, ours.time, 1e-3)
    away = np.min(np.abs(ours.time[:, None] - np.array([0.5, 1.0, 2.0, 3.0])), axis=1) > 1e-6
    for name in ("p", "r", "step_event_time"):
        np.testing.assert_allclose(ours[name][away], theirs[name][rows][away], atol=1e-9)


def test_record_events_adds_values_just_before_and_after(example):
    result = simulate(example("bouncing_ball"), record_events=True, output_interval=0.1)
    first_impact = math.sqrt(2 * 1.0 / 9.81)
    rows = np.flatnonzero(np.abs(result.time - first_impact) < 1e-9)
    assert len(rows) == 2
    before, after = rows
    assert result["v"][before] == pytest.approx(-math.sqrt(2 * 9.81), rel=1e-5)
    assert result["v"][after] == pytest.approx(0.7 * math.sqrt(2 * 9.81), rel=1e-5)
    assert result["bounces"][before] == 0 and result["bounces"][after] == 1
    assert np.all(np.diff(result.time) >= 0)


# ---------------------------------------------------------------------------------------
# The HybridSystem protocol with systems written in Python

class PythonBall:
    """A bouncing ball without FMI: impacts at t1 = sqrt(2 h0 / g), t_k+1 = t_k + 2 e^k t1."""
    n_states, n_indicators = 2, 1
    output_names, output_types = ["h", "v"], ["Real", "Real"]
    breakpoints = ()
    event_iterations = 0
    g, e = 9.81, 0.7

    def initialize(self, start_time, stop_time):
        return np.array([1.0, 0.0]), math.inf, False

    def derivatives(self, t, x):
        return np.array([x[1], -self.g])

    def indicators(self, t, x):
        return x[:1]

    def completed_step(self, t, x):
        return False, False

    def handle_event(self, t, x):
        self.event_iterations += 1
        h, v = x
        return (np.array([0.0, -self.e * v]) if h <= 0 and v < 0 else x), math.inf, False

    def outputs(self, times, states):
        return np.array(states, dtype=float)

    def terminate(self):
        pass

    def close(self):
        pass


def test_engine_runs_a_python_system_with_analytic_impacts():
    result = run(PythonBall(), DOPRI5(rtol=1e-10, atol=1e-10, max_step=0.05), start_time=0.0, stop_time=2.0,
                 output_times=output_grid(0.0, 2.0, 0.01))
    t1 = math.sqrt(2 / 9.81)
    impacts = [t1]
    while True:
        impacts.append(impacts[-1] + 2 * 0.7 ** len(impacts) * t1)
        if impacts[-1] > 2.0:
            impacts.pop()
            break
    np.testing.assert_allclose([t for t, _ in result.events], impacts, atol=1e-9)
    assert result.stats.state_events == len(impacts)
    # between impacts the height is a parabola through the last impact
    k = np.searchsorted(impacts, result.time) - 1
    speed = np.where(k >= 0, 0.7 ** (k + 1) * 9.81 * t1, 0.0)
    since = result.time - np.where(k >= 0, np.array(impacts)[np.maximum(k, 0)], 0.0)
    expected = np.where(k >= 0, speed * since - 0.5 * 9.81 * since ** 2, 1.0 - 0.5 * 9.81 * result.time ** 2)
    np.testing.assert_allclose(result["h"], expected, atol=1e-8)


class Clock:
    """Time events only: at t0 (twice, the second scheduled at the current time), one in
    the past, then every `period`; x' = 1 so the state counts time."""
    n_states, n_indicators = 1, 0
    output_names, output_types = ["x"], ["Real"]
    breakpoints = ()
    event_iterations = 0

    def __init__(self, schedule):
        self.schedule = list(schedule)
        self.seen = []

    def initialize(self, start_time, stop_time):
        return np.zeros(1), self.schedule.pop(0), False

    def derivatives(self, t, x):
        return np.ones(1)

    def indicators(self, t, x):
        return np.zeros(0)

    def completed_step(self, t, x):
        return False, False

    def handle_event(self, t, x):
        self.seen.append(t)
        return x, (self.schedule.pop(0) if self.schedule else math.inf), False

    def outputs(self, times, states):
        return np.array(states, dtype=float)

    def terminate(self):
        pass

    def close(self):
        pass


def test_time_events_at_the_start_and_in_the_past_are_handled_at_once():
    clock = Clock([0.0, 0.0, 0.3, 0.1, 0.6])
    result = run(clock, DOPRI5(), start_time=0.0, stop_time=1.0, output_times=output_grid(0.0, 1.0, 0.5))
    assert clock.seen == [0.0, 0.0, 0.3, 0.3, 0.6]     # 0.1 was already past at 0.3
    assert result.stats.time_events == 5
    np.testing.assert_allclose(result["x"], [0.0, 0.5, 1.0], atol=1e-12)


def test_a_model_that_never_lets_time_advance_is_an_error():
    clock = Clock([0.2] * 2000)
    with pytest.raises(FmuBuilderError, match="more than 1000 events at t=0.2"):
        run(clock, DOPRI5(), start_time=0.0, stop_time=1.0, output_times=[0.0, 1.0])


def test_a_system_with_its_own_derivatives_reuses_the_loop(example):
    """What a NeuralFMU does: the FMU plus a term added to a derivative. Adding -1 m/s^2 to
    der(v) must give the ball of an FMU with g = 10.81."""
    path = example("bouncing_ball")

    class HeavierBall(FmuSystem):
        def derivatives(self, t, x):
            return super().derivatives(t, x) + np.array([0.0, -1.0])

    with Fmu(path) as fmu:
        system = HeavierBall(fmu, variables=["h", "v", "bounces"])
        try:
            hybrid = run(system, DOPRI5(rtol=1e-10, atol=1e-10, max_step=0.06), start_time=0.0,
                         stop_time=3.0, output_times=output_grid(0.0, 3.0, 0.01))
        finally:
            system.close()
    reference = simulate(path, start_values={"g": 10.81}, rtol=1e-10, atol=1e-10, output_interval=0.01)
    assert [t for t, _ in hybrid.events] == pytest.approx([t for t, _ in reference.events], abs=1e-9)
    away = np.min(np.abs(hybrid.time[:, None] - np.array([t for t, _ in hybrid.events])), axis=1) > 1e-6
    np.testing.assert_allclose(hybrid["h"][away], reference["h"][away], atol=1e-8)


def test_one_recorded_point_holds_what_the_fmu_reports(example):
    """outputs() of one point (the engine's usual call, written into one row) and of several
    points (joined from parts) against the FMU's own getters, with the recorded columns in an
    order that mixes states, discrete Real and Boolean variables and computed outputs."""
    names = ["power", "driver.held_error", "speed", "standstill", "acceleration", "energy"]
    with Fmu(example("vldm")) as fmu:
        system = FmuSystem(fmu, variables=names, start_values={"cycle": 1})
        try:
            x0, _, _ = system.initialize(0.0, 10.0)
            x = x0 + np.linspace(0.5, 3.0, x0.size)     # moving: the computed outputs are not zero
            one = system.outputs((0.25,), x[None, :])
            several = system.outputs(np.array([0.25, 0.25]), np.array([x, x]))
            system.instance.set_time(0.25)
            system.instance.set_continuous_states(x)
            reported = np.array(system.instance.get(names), dtype=float)
        finally:
            system.close()
    assert one.shape == (1, len(names)) and several.shape == (2, len(names))
    assert reported[0] != 0.0      # the power, computed from the state
    np.testing.assert_array_equal(one[0], reported)
    np.testing.assert_array_equal(several, np.array([reported, reported]))


# ---------------------------------------------------------------------------------------
# Fixed-step convergence on the sampled plant, against its exact sampled-data solution

def exact_sampled_plant(stop_time):
    """States (i, w) at t_k = k Ts from the exact zero-order-hold discretization of the
    plant and the PI controller described in examples/sampled_plant/model.c."""
    R, L, K, J, b, setpoint, Kp, Ki, Ts, u_max = 1.0, 0.05, 0.5, 0.1, 0.05, 1.0, 0.5, 2.0, 0.01, 24.0
    A = np.array([[-R / L, -K / L], [K / J, -b / J]])
    B = np.array([1 / L, 0.0])
    Phi = expm(A * Ts)
    Gamma = np.linalg.solve(A, (Phi - np.eye(2)) @ B)
    x, integral, states = np.zeros(2), 0.0, []
    for _ in range(int(round(stop_time / Ts)) + 1):
        states.append(x.copy())
        error = setpoint - x[1]
        candidate = integral + Ki * Ts * error
        unclamped = Kp * error + candidate
        u = max(-u_max, min(u_max, unclamped))
        if u == unclamped:
            integral = candidate
        x = Phi @ x + Gamma * u
    return np.array(states)


@pytest.mark.parametrize("solver, steps, order", [("euler", (1e-3, 5e-4, 2.5e-4), 1),
                                                   ("rk4", (5e-3, 2.5e-3, 1.25e-3), 4)])
def test_fixed_step_convergence_order_on_the_sampled_plant(example, solver, steps, order):
    path = example("sampled_plant")
    exact = exact_sampled_plant(0.5)
    errors = []
    for h in steps:
        result = simulate(path, solver=solver, step_size=h, stop_time=0.5, output_interval=0.01)
        states = np.column_stack([result["i"], result["w"]])
        errors.append(np.max(np.abs(states - exact)))
    ratios = [errors[0] / errors[1], errors[1] / errors[2]]
    for ratio in ratios:
        assert 0.85 * 2 ** order < ratio < 1.15 * 2 ** order, (errors, ratios)


def test_adaptive_solver_matches_the_exact_sampled_plant(example):
    result = simulate(example("sampled_plant"), stop_time=0.5, rtol=1e-10, atol=1e-12, output_interval=0.01)
    states = np.column_stack([result["i"], result["w"]])
    np.testing.assert_allclose(states, exact_sampled_plant(0.5), rtol=0, atol=1e-8)
    assert result.stats.time_events == 50


# ---------------------------------------------------------------------------------------
# simulate(): defaults and user errors

def test_defaults_come_from_the_model_description(example):
    result = simulate(example("bouncing_ball"))
    assert result.names == ["h", "v", "bounces"]            # outputs, then states not yet listed
    assert result.time[0] == 0.0 and result.time[-1] == 3.0 and len(result.time) == 3001
    assert result.stats.solver == "dopri5" and result.stats.steps > 0
    assert result["bounces"].dtype == np.int64


@pytest.mark.parametrize("arguments, message", [
    (dict(stop_time=0.0), "stop time 0 is not after start time 0"),
    (dict(stop_time="soon"), "stop_time must be a number"),
    (dict(variables=["hh"]), r"unknown variable 'hh' .*did you mean 'h'"),
    (dict(start_values={"gg": 1.0}), "unknown variable 'gg'"),
    (dict(start_values={"g": "heavy"}), r"cannot set g \(Real\) to 'heavy'"),
    (dict(start_values={"der(h)": 1.0}), "cannot set a start value for 'der\\(h\\)'"),
    (dict(start_values={"g": "nan"}), "start value of g must be a finite number"),
    (dict(solver="cvode"), "unknown solver 'cvode'"),
    (dict(solver="euler", step_size=-1.0), "step_size must be positive"),
    (dict(output_interval=0.0), "output_interval must be positive"),
    (dict(output_interval=1e-9), "would record over"),
    (dict(rtol=-1.0), "rtol must be a finite number >= 0"),
    (dict(inputs={"time": [0.0], "u": [1.0]}), "'u' is not an input of 'bouncing_ball' \\(its inputs: none\\)"),
])
def test_bad_arguments_are_one_line_user_errors(example, arguments, message):
    with pytest.raises(FmuBuilderError, match=message) as error:
        simulate(example("bouncing_ball"), **arguments)
    assert "\n" not in str(error.value)


def test_bad_fmu_path_is_a_user_error(tmp_path):
    with pytest.raises(FmuBuilderError, match="no such file"):
        simulate(tmp_path / "missing.fmu")
