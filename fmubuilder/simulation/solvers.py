"""One-step ODE solvers for x' = f(t, x), behind one small interface.

A solver is started with `reset(f, t, x)` and restarted with `restart(t, x)` after every
event (an event may change x or the right-hand side), advanced by `step(t_limit)` one
accepted step at a time without passing `t_limit`, and asked for the state anywhere inside
its last step by `interpolate(t)`. That is all the event-handling loop needs, so solvers
stay free of FMI. `integrate` drives a solver over a plain ODE.

`f(t, x)` returns dx as a numpy array; the solver copies it or uses it up at once, so `f` may
reuse one output buffer between calls.

DOPRI5 evaluates f at the end of each step (its last stage is the next step's first); the
fixed-step solvers evaluate it when the next step or an interpolation needs it.
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np

from ..errors import FmuBuilderError

Rhs = Callable[[float, np.ndarray], np.ndarray]

# A step that would leave less than this fraction of itself before t_limit is stretched to
# t_limit instead, so rounding never produces a sliver step at an output or event time.
_SNAP = 1e-6


class Solver:
    """Interface shared by all solvers (see the module docstring)."""

    name = "solver"
    adaptive = False
    order = 0

    def __init__(self):
        self.t = self.t_prev = 0.0
        self.x = self.x_prev = np.zeros(0)
        self.dx = self.dx_prev = np.zeros(0)
        self.n_steps = 0        # accepted steps
        self.n_rejected = 0     # steps repeated with a smaller h (adaptive only)
        self.n_rhs = 0          # evaluations of f
        self._f: Rhs | None = None

    def reset(self, f: Rhs, t: float, x) -> None:
        """(Re)start at (t, x); forgets the previous step."""
        self._f = f
        self.t = self.t_prev = float(t)
        self.x = np.array(x, dtype=float)
        self.x_prev = self.x
        self.dx = np.array(f(self.t, self.x), dtype=float)
        self.dx_prev = self.dx
        self.n_rhs += 1

    def restart(self, t: float, x, keep_step: bool = False) -> None:
        """Restart after an event at (t, x) with the same f; an adaptive solver keeps its
        step-size estimate with keep_step, else starts no larger than it."""
        self.reset(self._f, t, x)

    def step(self, t_limit: float) -> float:
        """Take one accepted step ending at or before t_limit; returns the new time."""
        raise NotImplementedError

    def interpolate(self, t: float) -> np.ndarray:
        """The state at t in [t_prev, t] from the last step's dense output."""
        raise NotImplementedError

    def interpolate_many(self, times) -> np.ndarray:
        """The states at several times of the last step, one row each."""
        return np.array([self.interpolate(t) for t in times]).reshape(len(times), self.x.size)

    def stats(self) -> dict[str, int]:
        return {"steps": self.n_steps, "rejected_steps": self.n_rejected, "rhs_evaluations": self.n_rhs}

    def _theta(self, t: float) -> tuple[float, float]:
        h = self.t - self.t_prev
        return (1.0 if h == 0.0 else (t - self.t_prev) / h), h


class FixedStepSolver(Solver):
    """Steps of a fixed size h, shortened only to land exactly on t_limit."""

    def __init__(self, step_size: float):
        super().__init__()
        if not step_size > 0.0 or not math.isfinite(step_size):
            raise FmuBuilderError(f"step size must be a positive number, got {step_size}")
        self.h = float(step_size)

    def reset(self, f: Rhs, t: float, x) -> None:
        self._f = f
        self.restart(t, x)

    def restart(self, t: float, x, keep_step: bool = False) -> None:
        self.t = self.t_prev = float(t)
        self.x = self.x_prev = np.array(x, dtype=float)

    def step(self, t_limit: float) -> float:
        t, x = self.t, self.x
        h = t_limit - t
        if h > self.h * (1.0 + _SNAP):
            h = self.h
            t_new = t + h
        else:
            t_new = t_limit
        x_new = self._advance(t, x, h)
        self.t_prev, self.x_prev = t, x
        self.t, self.x = t_new, x_new
        self.n_steps += 1
        return t_new

    def _advance(self, t: float, x: np.ndarray, h: float) -> np.ndarray:
        """The state after a step of length h from (t, x) (the current point)."""
        raise NotImplementedError


class Euler(FixedStepSolver):
    """Explicit (forward) Euler, order 1; linear interpolation inside a step."""

    name = "euler"
    order = 1

    def _advance(self, t, x, h):
        # f's buffer is read at once, so no copy of it (the derivative is kept by RK4 only)
        self.n_rhs += 1
        return x + h * np.asarray(self._f(t, x), dtype=float)

    def interpolate(self, t: float) -> np.ndarray:
        theta, _ = self._theta(t)
        return self.x_prev + theta * (self.x - self.x_prev)


class RK4(FixedStepSolver):
    """Classical 4-stage Runge-Kutta, order 4; cubic Hermite interpolation inside a step
    from the derivatives at both ends (third-order accurate; the end derivative is the
    next step's first stage, so it costs nothing extra when the integration goes on)."""

    name = "rk4"
    order = 4

    # The derivative at the current point is evaluated when the next step or an interpolation
    # needs it, not at the end of a step: after an event it would have to be evaluated again anyway.
    _dx_current = False     # whether self.dx belongs to (self.t, self.x)

    def restart(self, t: float, x, keep_step: bool = False) -> None:
        super().restart(t, x)
        self._dx_current = False

    def _derivative_here(self) -> np.ndarray:
        if not self._dx_current:
            self.dx = np.array(self._f(self.t, self.x), dtype=float)
            self.n_rhs += 1
            self._dx_current = True
        return self.dx

    def _advance(self, t, x, h):
        k1 = self.dx_prev = self._derivative_here()
        self._dx_current = False        # the next point's is evaluated when needed
        f = self._f
        self.n_rhs += 3
        return rk4_step(lambda t, x: np.array(f(t, x), dtype=float), t, x, k1, h)

    def interpolate(self, t: float) -> np.ndarray:
        if self.t == self.t_prev:       # no step since the last reset
            return self.x.copy()
        self._derivative_here()
        return _hermite(self, t)


def _hermite(solver: Solver, t: float) -> np.ndarray:
    theta, h = solver._theta(t)
    return hermite(theta, h, solver.x_prev, solver.dx_prev, solver.x, solver.dx)


# The step and the dense output of the fixed-step solvers as plain arithmetic, so that numpy
# arrays (this module) and torch tensors (the NeuralFMU's differentiable solver) share them.

def rk4_step(f: Rhs, t, x, k1, h, t_step=None):
    """x + h/6 (k1 + 2 k2 + 2 k3 + k4), given k1 = f(t, x). `h` scales the stages (a tensor
    where the step length carries a gradient); `t_step` (default h) advances the time."""
    t_step = h if t_step is None else t_step
    half = 0.5 * h
    k2 = f(t + 0.5 * t_step, x + half * k1)
    k3 = f(t + 0.5 * t_step, x + half * k2)
    k4 = f(t + t_step, x + h * k3)
    return x + h / 6.0 * (k1 + 2.0 * (k2 + k3) + k4)


def hermite(theta, h, x0, d0, x1, d1):
    """Cubic Hermite interpolation at t0 + theta h between (x0, d0) and (x1, d1)."""
    t2 = theta * theta
    t3 = t2 * theta
    return ((2 * t3 - 3 * t2 + 1) * x0 + (t3 - 2 * t2 + theta) * h * d0
            + (-2 * t3 + 3 * t2) * x1 + (t3 - t2) * h * d1)


# Dormand-Prince 5(4). Row i < 5 of _M gives stage i + 2 from the stage derivatives
# k1..k7 (zero-padded, so each row is one dot product with all of K); row 5 holds the
# 5th-order weights (x_new; its derivative is stage 7, first-same-as-last) and row 6 the
# difference to the embedded 4th-order weights, which estimates the local error.
_C = [0.0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0, 1.0]
_M = np.array([
    [1 / 5, 0, 0, 0, 0, 0, 0],
    [3 / 40, 9 / 40, 0, 0, 0, 0, 0],
    [44 / 45, -56 / 15, 32 / 9, 0, 0, 0, 0],
    [19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729, 0, 0, 0],
    [9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656, 0, 0],
    [35 / 384, 0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84, 0],
    [71 / 57600, 0, -71 / 16695, 71 / 1920, -17253 / 339200, 22 / 525, -1 / 40],
])
# Continuous extension of order 4 (Shampine/Dormand-Prince): over a step of size h,
# x(t0 + theta h) = x0 + h * sum_i k_i * (P[i] @ [theta, theta^2, theta^3, theta^4]).
_P = np.array([
    [1.0, -8048581381 / 2820520608, 8663915743 / 2820520608, -12715105075 / 11282082432],
    [0.0, 0.0, 0.0, 0.0],
    [0.0, 131558114200 / 32700410799, -68118460800 / 10900136933, 87487479700 / 32700410799],
    [0.0, -1754552775 / 470086768, 14199869525 / 1410260304, -10690763975 / 1880347072],
    [0.0, 127303824393 / 49829197408, -318862633887 / 49829197408, 701980252875 / 199316789632],
    [0.0, -282668133 / 205662961, 2019193451 / 616988883, -1453857185 / 822651844],
    [0.0, 40617522 / 29380423, -110615467 / 29380423, 69997945 / 29380423],
])
_POWERS = np.arange(1, 5)


class DOPRI5(Solver):
    """Adaptive explicit Runge-Kutta of order 5 with an embedded order-4 error estimate.

    The local error estimate, scaled per component by atol + rtol * max(|x_old|, |x_new|),
    must have an RMS norm <= 1 for a step to be accepted; the next step size follows the
    standard controller h * clip(0.9 * err^(-1/5), 0.2, 10), not growing right after a
    rejection. After an event, `restart` estimates a new first step (capped by the step
    size reached so far) or, with keep_step, reuses that step size directly: cheap for
    frequent time events (sampled controllers), while a state event, which often
    reverses a motion, starts small again so that the next crossing is not stepped over.
    """

    name = "dopri5"
    adaptive = True
    order = 5

    def __init__(self, rtol: float = 1e-6, atol: float = 1e-8, max_step: float = math.inf,
                 first_step: float | None = None):
        super().__init__()
        for label, value in (("rtol", rtol), ("atol", atol)):
            if not (value >= 0.0 and math.isfinite(value)):
                raise FmuBuilderError(f"{label} must be a finite number >= 0, got {value}")
        if rtol == 0.0 and atol == 0.0:
            raise FmuBuilderError("rtol and atol cannot both be 0; give a positive tolerance, e.g. rtol=1e-6")
        if not max_step > 0.0:
            raise FmuBuilderError(f"max_step must be positive, got {max_step}")
        self.rtol, self.atol, self.max_step = float(rtol), float(atol), float(max_step)
        self.first_step = first_step
        self.h = 0.0                    # proposed size of the next step
        # Two stage buffers used in turn: the last step's stays intact for dense output
        # while the next step fills the other.
        self._K = np.zeros((7, 0))
        self._K_last = np.zeros((7, 0))
        self._Q = None                  # dense-output coefficients of the last step, on demand
        self._stepped = False
        self._abs_x = np.zeros(0)

    def reset(self, f: Rhs, t: float, x) -> None:
        self._start(f, t, x, self.first_step)

    def restart(self, t: float, x, keep_step: bool = False) -> None:
        previous = self.h
        self._start(self._f, t, x, previous if keep_step and previous > 0.0 else None)
        if previous > 0.0:
            self.h = min(self.h, previous)

    def _start(self, f: Rhs, t: float, x, first_step: float | None) -> None:
        super().reset(f, t, x)
        n = self.x.size
        if self._K.shape[1] != n:
            self._K, self._K_last = np.zeros((7, n)), np.zeros((7, n))
        self._K[0] = self.dx
        self._Q = None
        self._stepped = False
        self._abs_x = np.abs(self.x)
        self.h = first_step or self._initial_step()

    def _initial_step(self) -> float:
        """Hairer's starting-step heuristic: one extra f evaluation."""
        x, dx, t = self.x, self.dx, self.t
        if x.size == 0:
            return self.max_step
        scale = self.atol + self.rtol * np.abs(x)
        d0 = _rms(x / scale)
        d1 = _rms(dx / scale)
        h0 = 1e-6 if d0 < 1e-5 or d1 < 1e-5 else 0.01 * d0 / d1
        h0 = min(h0, self.max_step)
        dx1 = self._f(t + h0, x + h0 * dx)
        self.n_rhs += 1
        d2 = _rms((dx1 - dx) / scale) / h0
        h1 = max(1e-6, h0 * 1e-3) if max(d1, d2) <= 1e-15 else (0.01 / max(d1, d2)) ** (1 / 5)
        return min(100 * h0, h1, self.max_step)

    def step(self, t_limit: float) -> float:
        f, K, x, t = self._f, self._K, self.x, self.t
        n = x.size
        h_wanted = h = min(self.h, self.max_step)
        rejected = False
        if not h > 0.0:     # no step size to start with (a degenerate tolerance)
            raise step_size_underflow(t, h)
        while True:
            remaining = t_limit - t
            if h >= remaining * (1.0 - _SNAP):
                h, t_new = remaining, t_limit
            else:
                t_new = t + h
            hM = h * _M
            for i in range(5):
                K[i + 1] = f(t + _C[i + 1] * h, x + hM[i].dot(K))
            x_new = x + hM[5].dot(K)
            K[6] = f(t_new, x_new)
            self.n_rhs += 6
            if n:
                abs_new = np.abs(x_new)
                error = hM[6].dot(K) / (self.atol + self.rtol * np.maximum(self._abs_x, abs_new))
                err = math.sqrt(error.dot(error) / n)
            else:
                err = 0.0
            if err <= 1.0:
                break
            self.n_rejected += 1
            rejected = True
            if not math.isfinite(err):      # f failed somewhere: retreat, clear the stages
                K[1:] = 0.0
                h *= 0.2
            else:
                h *= max(0.2, 0.9 * err ** -0.2)
            h_wanted = h
            if not h >= 1e-14 * max(1.0, abs(t)):     # NaN too: no step size is left
                raise step_size_underflow(t, h)
        factor = 10.0 if err == 0.0 else min(10.0, max(0.2, 0.9 * err ** -0.2))
        if rejected:
            factor = min(1.0, factor)
        h_next = h * factor
        if t_new == t_limit and h < h_wanted:
            # A step shortened to land on t_limit says nothing against the longer one.
            h_next = max(h_next, h_wanted)
        self.h = min(h_next, self.max_step)
        self.t_prev, self.x_prev, self.dx_prev = t, x, K[0]
        self.t, self.x, self.dx = t_new, x_new, K[6]
        if n:
            self._abs_x = abs_new
        # Swap the stage buffers; the next step starts from this one's last stage.
        self._K, self._K_last = self._K_last, K
        self._K[0] = K[6]
        self._Q = None
        self._stepped = True
        self.n_steps += 1
        return t_new

    def _dense(self) -> np.ndarray:
        if self._Q is None:
            self._Q = self._K_last.T @ _P
        return self._Q

    def interpolate(self, t: float) -> np.ndarray:
        if not self._stepped:       # no step since the last reset
            return self.x.copy()
        theta, h = self._theta(t)
        powers = np.array([theta, theta * theta, theta ** 3, theta ** 4])
        return self.x_prev + h * self._dense().dot(powers)

    def interpolate_many(self, times) -> np.ndarray:
        if not self._stepped:
            return np.tile(self.x, (len(times), 1))
        h = self.t - self.t_prev
        theta = (np.asarray(times, dtype=float) - self.t_prev) / h if h else np.ones(len(times))
        return self.x_prev + h * ((theta[:, None] ** _POWERS) @ self._dense().T)


def step_size_underflow(t: float, h: float) -> FmuBuilderError:
    return FmuBuilderError(
        f"step size underflow at t={t:.12g} (error test fails for h={h:.3g}); the model may be stiff or "
        "discontinuous without an event indicator: loosen rtol/atol or use a fixed-step solver")


def _rms(v: np.ndarray) -> float:
    return math.sqrt(v.dot(v) / v.size)


SOLVERS = {"euler": Euler, "rk4": RK4, "dopri5": DOPRI5}


def make_solver(name: str, *, rtol: float = 1e-6, atol: float = 1e-8, step_size: float | None = None,
                max_step: float = math.inf) -> Solver:
    """A solver by (case-insensitive) name: 'euler', 'rk4' or 'dopri5'."""
    key = str(name).lower()
    if key not in SOLVERS:
        raise FmuBuilderError(f"unknown solver '{name}'; choose one of {', '.join(SOLVERS)}")
    if key == "dopri5":
        return DOPRI5(rtol=rtol, atol=atol, max_step=max_step)
    if step_size is None:
        raise FmuBuilderError(f"solver '{key}' needs a step size; pass step_size")
    return SOLVERS[key](step_size)


def integrate(solver: Solver, f: Rhs, t_eval, x0) -> np.ndarray:
    """Solve x' = f(t, x), x(t_eval[0]) = x0 and return x at every t_eval (rows).

    A plain-ODE driver for tests and callers without events: outputs come from the
    solver's dense output, so they do not shorten its steps.
    """
    t_eval = np.asarray(t_eval, dtype=float)
    if t_eval.ndim != 1 or t_eval.size == 0 or np.any(np.diff(t_eval) < 0):
        raise FmuBuilderError("t_eval must be a non-empty, non-decreasing 1-D array of times")
    solver.reset(f, t_eval[0], x0)
    out = np.empty((t_eval.size, solver.x.size))
    out[0] = solver.x
    i = 1
    while i < t_eval.size:
        t = solver.step(t_eval[-1])
        while i < t_eval.size and t_eval[i] <= t:
            out[i] = solver.x if t_eval[i] == t else solver.interpolate(t_eval[i])
            i += 1
    return out
