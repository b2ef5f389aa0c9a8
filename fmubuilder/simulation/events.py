"""The event sequence of FMI 2.0 Model Exchange, written once (`EventSequence`) for the engine and
the NeuralFMU's batch solver, and its shared pieces (docs/ARCHITECTURE.md, "Event handling").

Crossing convention (the one of fmpy and FMUSDK-style importers): indicator i fires
between z0 (at the step start) and z1 when

    z0 < 0 and z1 >= 0      or      z0 > 0 and z1 <= 0

so reaching exactly 0 fires, while leaving exactly 0 does not (an indicator that an event
has just reset to 0, like a bouncing ball's height, must not fire again at once).

Location brackets the earliest crossing by a vector Illinois (modified regula falsi)
iteration on the indicators evaluated along the solver's dense output, and returns the
right end of the final bracket: there the crossing has happened, so the model's event
update sees the condition that fired, and all indicators crossed by then are one event.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from ..errors import FmuBuilderError
from ..fmi.instance import EventInfo

# Time events at one instant beyond this many mean the model never lets time advance; steps cut at
# a state event in a row beyond this many, that it chatters (Zeno behaviour).
MAX_EVENTS_AT_ONE_TIME = 1000
MAX_CUT_STEPS_IN_A_ROW = 100
STEP, EVENT = "step", "event"     # what the sequence asks its driver for
# Times closer than this times the experiment's time scale (time_tolerance) are one instant: the
# rounding of output, grid, input and event times, far below any step.
RELATIVE_TIME_TOLERANCE = 1e-12
_TIME_EVENT, _STATE_EVENT, _STEP_EVENT = (EVENT, "time"), (EVENT, "state"), (EVENT, "step")


class EventSequence:
    """Where one instance stands in the event sequence (t, its next time event, the indicators as
    the reference of the next step's sign changes, terminated), and the sequence, written once:
    `towards(limit, driver)` walks the instance to `limit`, yielding what its driver does:

        (EVENT, "time")   a time event due (within the tolerance: that instant exactly), first
        (STEP, end)       a step towards end = min(next time event, driver.step_limit(seq, limit));
                          the driver sends back the time reached (DOPRI5 may stop short). Then: the
                          indicators at its end; a sign change cuts it at the earliest crossing
                          (driver.cut_at_state_event, by `locate`); fmi2CompletedIntegratorStep
                          (driver.completed_step) unless the step had length zero; a time event due
                          then takes a crossing or step event with it, else
        (EVENT, "state" | "step"), or with no event driver.stepped_on(seq) (if not None)

    For an event the driver runs event mode, restarts its solver on the states it left and sets
    next_event, z and terminated. Times within `tolerance(t)` are one instant (time_tolerance,
    `scale` the experiment's time_scale)."""

    def __init__(self, t: float, next_event: float, z, counts: dict, scale: float, index: int = 0):
        self.t, self.next_event, self.z = t, next_event, z
        self.index = index                  # which instance of the driver's (a batch element)
        self.counts = counts                # time_events, state_events, step_events (shared by a batch)
        self.time_scale = scale
        self.terminated = False
        self.pending_step = False           # step once more even at the limit (set by a driver)
        self.events_here = 0                # time events since the last step
        self.cuts_in_a_row = 0

    def drive(self, limit: float, driver) -> None:
        """`towards` for a driver of one instance, which does each request at once:
        driver.step(seq, end) -> the time reached, driver.event(seq, kind)."""
        walk = self.towards(limit, driver)
        send, step, event = walk.send, driver.step, driver.event
        try:
            kind, what = next(walk)
            while True:
                if kind is STEP:
                    kind, what = send(step(self, what))
                else:
                    event(self, what)
                    kind, what = send(None)
        except StopIteration:
            pass

    def tolerance(self, t: float) -> float:
        return time_tolerance(t, self.time_scale)

    def towards(self, limit: float, driver):
        # The hot loop of every simulation: one pass per step, so no call it can do without.
        # tolerance(t) inline: rel * scale while |t| <= scale, where the experiment keeps it.
        rel, scale = RELATIVE_TIME_TOLERANCE, self.time_scale
        floor = rel * scale
        at_limit = limit - time_tolerance(limit, scale)
        step_limit, completed_step = driver.step_limit, driver.completed_step
        indicators_at_end, stepped_on = driver.indicators_at_end, driver.stepped_on
        counts = self.counts
        while not self.terminated:
            t, next_event = self.t, self.next_event
            if next_event <= t + (floor if -scale <= t <= scale else rel * abs(t)):
                if next_event > t:
                    self.t = next_event     # a time event a rounding error ahead is now
                self.events_here += 1
                if self.events_here > MAX_EVENTS_AT_ONE_TIME:
                    raise FmuBuilderError(
                        f"more than {MAX_EVENTS_AT_ONE_TIME} events at t={self.t:.17g}: the model keeps "
                        "scheduling events without letting time advance; check its time events")
                counts["time_events"] += 1
                yield _TIME_EVENT
                continue
            if t >= at_limit and not self.pending_step:
                return
            end = step_limit(self, limit)
            t_end = yield STEP, (next_event if next_event < end else end)
            self.pending_step = False
            state_event = False
            z = self.z
            if z is not None:      # the indicators at the step's end: a sign change cuts it
                z_end = indicators_at_end(self, t_end)
                product = z * z_end     # a crossing needs a product <= 0: most steps ruled out at once (NaN: checked)
                if not product.item(product.argmin()) > 0.0 and crossed(z, z_end).any():
                    state_event = True
                    t_end, z_end = self._cut(t, t_end, z_end, driver)
                else:
                    self.cuts_in_a_row = 0
                self.z = z_end
            self.t = t_end
            self.events_here = 0
            step_event = False
            if t_end != t:    # not a step of length zero (which only carries an event time's gradient)
                step_event, terminated = completed_step(self, state_event)
                if terminated:
                    self.terminated = True
                    return
            if self.next_event <= t_end + (floor if -scale <= t_end <= scale else rel * abs(t_end)):
                continue    # a time event is due now: the next pass handles it, and any crossing with it
            if state_event:
                counts["state_events"] += 1
                counts["step_events"] += step_event
                yield _STATE_EVENT
            elif step_event:
                counts["step_events"] += 1
                yield _STEP_EVENT
            elif stepped_on is not None:
                stepped_on(self)

    def _cut(self, t_start: float, t_end: float, z_end, driver):
        """The step cut at its earliest state event: (its end, the indicators there)."""
        self.cuts_in_a_row += 1
        if self.cuts_in_a_row > MAX_CUT_STEPS_IN_A_ROW:
            raise FmuBuilderError(
                f"more than {MAX_CUT_STEPS_IN_A_ROW} state events in a row at t={t_end:.6g} (chattering "
                "or Zeno behaviour); reduce the step size or fix the model")
        tolerance = max(self.tolerance(t_end), 1e-12 * (t_end - t_start))
        return driver.cut_at_state_event(self, t_start, t_end, z_end, tolerance)


def time_scale(start: float, stop: float) -> float:
    """The scale of an experiment's times from start to stop: max(|start|, |stop|, stop - start)."""
    return max(abs(start), abs(stop), stop - start)


def time_tolerance(t: float, scale: float) -> float:
    """How close to t another time is the same instant, in an experiment of that time scale: one
    tolerance for every driver of the event sequence (engine and batch) and the engine's outputs."""
    return RELATIVE_TIME_TOLERANCE * max(scale, abs(t))


def event_mode(instance, *, entered: bool = False, before_iteration: Callable[[], None] | None = None,
               after_iteration: Callable[[], None] | None = None,
               resume_on_terminate: bool = False) -> EventInfo:
    """Event mode for one FMI 2.0 Model-Exchange instance standing at the event's (t, x):
    fmi2EnterEventMode (not when `entered`: fmi2ExitInitializationMode leaves the instance in event
    mode), `before_iteration()` (what may change in event mode only: discrete inputs, tunable
    parameters), the event iteration (fmi2NewDiscreteStates until no new discrete states are
    needed), `after_iteration()`, fmi2EnterContinuousTimeMode.

    Returns what the event left (the EventInfo of FmuInstance.update_discrete_states, merged over
    the iteration's passes): whether the states changed (re-read them), the next time event,
    whether the FMU asks to terminate. When it does, the instance stays in event mode for
    fmi2Terminate; with `resume_on_terminate` it goes back to continuous-time mode all the same
    (a batch keeps a terminated element, frozen, whose instance is still evaluated)."""
    if not entered:
        instance.enter_event_mode()
    if before_iteration is not None:
        before_iteration()
    info = instance.update_discrete_states()
    if not info.terminate_simulation or resume_on_terminate:
        if after_iteration is not None:
            after_iteration()
        instance.enter_continuous_time_mode()
    return info


def crossed(z0: np.ndarray, z1: np.ndarray) -> np.ndarray:
    """Mask of the indicators that fire between z0 and z1 (see the module docstring)."""
    return ((z0 < 0.0) & (z1 >= 0.0)) | ((z0 > 0.0) & (z1 <= 0.0))


def locate(indicators_at: Callable[[float], np.ndarray], t0: float, z0: np.ndarray,
           t1: float, z1: np.ndarray, tolerance: float, max_iterations: int = 200):
    """Earliest time in (t0, t1] at which some indicator fires.

    `indicators_at(t)` evaluates the indicators at time t (on the interpolated state);
    z0, z1 are their values at t0 and t1, with at least one crossing between them.
    Returns (t_event, z_event, fired, evaluations): t_event is within `tolerance` after the
    earliest crossing, `fired` is the mask of the indicators that fired by t_event.
    """
    ta, tb = t0, t1
    za = np.array(z0, dtype=float)       # values at the bracket's left end (before any crossing)
    zb = np.array(z1, dtype=float)       # values at its right end (some crossing happened)
    wa = np.ones_like(za)                # Illinois weights on the retained ends
    wb = np.ones_like(zb)
    last_side = 0
    evaluations = 0
    width_before = tb - ta
    while tb - ta > tolerance and evaluations < max_iterations:
        fire = crossed(z0, zb)
        t_trial = _secant_earliest(ta, tb, wa[fire] * za[fire], wb[fire] * zb[fire])
        if evaluations % 3 == 2 and tb - ta > 0.5 * width_before:
            t_trial = 0.5 * (ta + tb)     # slow progress: bisect to keep the bracket shrinking
        if evaluations % 3 == 2:
            width_before = tb - ta
        margin = 0.25 * tolerance
        t_trial = min(max(t_trial, ta + margin), tb - margin)
        z_trial = np.array(indicators_at(t_trial), dtype=float)
        evaluations += 1
        if crossed(z0, z_trial).any():
            tb, zb = t_trial, z_trial
            wb[:] = 1.0
            if last_side == 1:
                wa *= 0.5                  # the left end stayed twice: damp it
            last_side = 1
        else:
            ta, za = t_trial, z_trial
            wa[:] = 1.0
            if last_side == -1:
                wb *= 0.5
            last_side = -1
    return tb, zb, crossed(z0, zb), evaluations


def _secant_earliest(ta: float, tb: float, za: np.ndarray, zb: np.ndarray) -> float:
    """The earliest of the secant roots of the firing indicators inside [ta, tb]."""
    denominator = zb - za
    with np.errstate(divide="ignore", invalid="ignore"):
        roots = tb - zb * (tb - ta) / denominator
    roots = roots[np.isfinite(roots)]
    return float(min(max(roots.min(), ta), tb)) if roots.size else 0.5 * (ta + tb)
