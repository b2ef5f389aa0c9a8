"""The ODE solvers on problems with closed-form solutions (no FMI involved)."""
import math

import numpy as np
import pytest

from fmubuilder.errors import FmuBuilderError
from fmubuilder.simulation.solvers import DOPRI5, RK4, Euler, integrate, make_solver


def decay(rate):
    return lambda t, x: -rate * x


def oscillator(omega):
    """x'' = -omega^2 x as a first-order system; x(0) = 1, x'(0) = 0 gives cos(omega t)."""
    return lambda t, x: np.array([x[1], -omega * omega * x[0]])


def oscillator_exact(t, omega):
    return np.column_stack([np.cos(omega * t), -omega * np.sin(omega * t)])


def test_dopri5_exponential_decay_within_tolerance():
    t = np.linspace(0.0, 5.0, 51)
    for rtol in (1e-4, 1e-6, 1e-8, 1e-10):
        x = integrate(DOPRI5(rtol=rtol, atol=rtol * 1e-3), decay(1.3), t, [2.0])
        exact = 2.0 * np.exp(-1.3 * t)
        assert np.max(np.abs(x[:, 0] - exact) / exact) < 50 * rtol


def test_dopri5_harmonic_oscillator_and_error_shrinks_with_tolerance():
    t = np.linspace(0.0, 20.0, 201)
    errors = []
    for tol in (1e-5, 1e-7, 1e-9):
        solver = DOPRI5(rtol=tol, atol=tol)
        x = integrate(solver, oscillator(2.0), t, [1.0, 0.0])
        errors.append(np.max(np.abs(x - oscillator_exact(t, 2.0))))
        assert errors[-1] < 100 * tol * 2.0 * 20.0      # global error ~ tol * amplitude * length
    assert errors[0] > errors[1] > errors[2]


def test_dopri5_steps_grow_on_a_polynomial_it_integrates_exactly():
    # x' = 3 t^2: a 5th-order method is exact, the error estimate is ~0, steps grow 10x.
    solver = DOPRI5(rtol=1e-10, atol=1e-12, max_step=0.5)
    x = integrate(solver, lambda t, x: np.array([3.0 * t * t]), [0.0, 10.0], [0.0])
    assert x[-1, 0] == pytest.approx(1000.0, rel=1e-12)
    assert solver.n_rejected == 0
    assert solver.n_steps < 40


@pytest.mark.parametrize("solver_class, order, steps", [(Euler, 1, (0.01, 0.005, 0.0025)),
                                                         (RK4, 4, (0.1, 0.05, 0.025))])
def test_fixed_step_convergence_order(solver_class, order, steps):
    t = np.array([0.0, 3.0])
    errors = [np.max(np.abs(integrate(solver_class(h), oscillator(1.5), t, [1.0, 0.0])[-1]
                            - oscillator_exact(t, 1.5)[-1])) for h in steps]
    ratios = [errors[0] / errors[1], errors[1] / errors[2]]
    expected = 2.0 ** order
    for ratio in ratios:
        assert expected * 0.85 < ratio < expected * 1.15, ratios


def test_fixed_step_lands_on_the_limit_without_sliver_steps():
    solver = Euler(0.1)
    solver.reset(decay(1.0), 0.0, [1.0])
    times = [solver.step(0.3) for _ in range(3)]
    assert times[-1] == 0.3                 # 0.1 + 0.1 + 0.1 != 0.3 in floating point
    assert solver.n_steps == 3


def test_dopri5_dense_output_is_fourth_order_and_exact_at_the_step_end():
    f = lambda t, x: np.array([math.cos(t)])
    errors = []
    for h in (0.4, 0.2, 0.1):
        solver = DOPRI5(rtol=1.0, atol=1.0, first_step=h)   # loose: the step is taken as given
        solver.reset(f, 0.0, [0.0])
        t_end = solver.step(10.0)
        assert t_end == pytest.approx(h)
        assert solver.interpolate(t_end)[0] == pytest.approx(solver.x[0], abs=1e-15)
        mid = np.linspace(0.0, h, 9)[1:-1]
        dense = solver.interpolate_many(mid)[:, 0]
        np.testing.assert_allclose(dense, [solver.interpolate(t)[0] for t in mid], rtol=0, atol=1e-15)
        errors.append(np.max(np.abs(dense - np.sin(mid))))
    # local error of a 4th-order interpolant: O(h^5), a ratio of 32 per halving
    assert errors[0] / errors[1] > 20 and errors[1] / errors[2] > 20


def test_hermite_interpolation_of_rk4_matches_cubic_accuracy():
    solver = RK4(0.05)
    solver.reset(oscillator(1.0), 0.0, [1.0, 0.0])
    solver.step(1.0)
    t_mid = 0.025
    assert np.max(np.abs(solver.interpolate(t_mid) - oscillator_exact(np.array([t_mid]), 1.0)[0])) < 1e-7


def test_solvers_handle_a_system_without_states():
    for solver in (DOPRI5(max_step=0.25), Euler(0.1), RK4(0.1)):
        x = integrate(solver, lambda t, x: np.zeros(0), [0.0, 1.0], np.zeros(0))
        assert x.shape == (2, 0)


def test_dopri5_reports_step_size_underflow_on_a_failing_rhs():
    def blows_up(t, x):
        return np.array([math.nan]) if t > 0.5 else -x
    solver = DOPRI5(rtol=1e-6)
    solver.reset(blows_up, 0.0, [1.0])
    with pytest.raises(FmuBuilderError, match="step size underflow"):
        while solver.t < 1.0:
            solver.step(1.0)


def test_dopri5_restart_keeps_the_step_size_when_asked():
    solver = DOPRI5(rtol=1e-8, atol=1e-8)
    solver.reset(decay(1.0), 0.0, [1.0])
    for _ in range(5):
        solver.step(100.0)
    h = solver.h
    solver.restart(solver.t, solver.x, keep_step=True)
    assert solver.h == h
    solver.restart(solver.t, solver.x)
    assert 0 < solver.h <= h


def test_bad_solver_arguments_are_user_errors():
    with pytest.raises(FmuBuilderError, match="unknown solver 'cvode'"):
        make_solver("cvode")
    with pytest.raises(FmuBuilderError, match="step size must be a positive"):
        Euler(0.0)
    with pytest.raises(FmuBuilderError, match="rtol must be"):
        DOPRI5(rtol=-1.0)
    with pytest.raises(FmuBuilderError, match="needs a step size"):
        make_solver("rk4")
    with pytest.raises(FmuBuilderError, match="non-decreasing"):
        integrate(Euler(0.1), decay(1.0), [1.0, 0.0], [1.0])
