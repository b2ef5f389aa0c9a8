"""The hybrid simulation loop with FMI 2.0 Model-Exchange event semantics (the event sequence
of events.py, driven for one instance with any solver of solvers.py and an output grid).

    initialise (the system runs its initial event iteration)
    loop:
        time events due now (at t0, in the past, or just reached) -> event mode
        record the output times reached (after the events at that time)
        stop at the stop time
        one solver step towards min(next time event, input kink, stop[, next output for
            fixed-step solvers])
        a sign change of an event indicator -> locate the earliest one on the dense output,
            cut the step there
        record the output times inside the step (dense output)
        completed-integrator-step -> maybe a step event or termination
        state or step event -> event mode; every event restarts the solver on the
            states the event left (they may have been reset)

Time comparisons use a tolerance of 1e-12 times the experiment's scale, so output times,
time events and the stop time that differ only by rounding are the same instant.
"""
from __future__ import annotations

import math
import time as wallclock
from bisect import bisect_left, bisect_right

import numpy as np

from ..errors import FmuBuilderError
from .events import cut_at_state_event
from .results import SimulationResult, SimulationStats
from .solvers import Solver
from .system import HybridSystem

# Events at one instant beyond this many mean the model never lets time advance.
MAX_EVENTS_AT_ONE_TIME = 1000


def run(system: HybridSystem, solver: Solver, *, start_time: float, stop_time: float,
        output_times, record_events: bool = False) -> SimulationResult:
    """Simulate `system` from start_time to stop_time, sampling the outputs at output_times
    (sorted, within [start_time, stop_time]). With record_events the outputs just before
    and after each event are added as extra rows at the event time."""
    started = wallclock.perf_counter()
    stats = SimulationStats(solver=solver.name)
    recorder = _Recorder(system.output_names, system.output_types)
    loop = _Loop(system, solver, start_time, stop_time, np.asarray(output_times, dtype=float),
                 recorder, stats, record_events)
    try:
        loop.run()
    finally:
        stats.wall_time = wallclock.perf_counter() - started
    for key, value in solver.stats().items():
        setattr(stats, key, value)
    stats.event_iterations = system.event_iterations
    time, values = recorder.arrays()
    return SimulationResult(time=time, values=values, stats=stats,
                            terminated_early=loop.terminated and loop.t < stop_time - loop.eps,
                            stop_time=loop.t, events=loop.events)


class _Loop:
    """State of one simulation run; `run` is the loop of the module docstring."""

    def __init__(self, system, solver, start_time, stop_time, output_times, recorder, stats, record_events):
        self.system, self.solver = system, solver
        self.start, self.stop = float(start_time), float(stop_time)
        self.eps = 1e-12 * max(abs(self.start), abs(self.stop), self.stop - self.start)
        self.outputs = output_times.tolist()
        self.recorder, self.stats, self.record_events = recorder, stats, record_events
        self.breakpoints = [float(b) for b in sorted(system.breakpoints)
                            if self.start + self.eps < b < self.stop - self.eps]
        self.events: list[tuple[float, str]] = []
        self.terminated = False
        self.t = self.start

    def run(self) -> None:
        system, solver, stats = self.system, self.solver, self.stats
        eps, stop = self.eps, self.stop
        outputs, n_out = self.outputs, len(self.outputs)
        breakpoints, n_bp = self.breakpoints, len(self.breakpoints)
        f = system.derivatives
        n_z = system.n_indicators
        indicators = system.indicators
        record = self.recorder.add
        outputs_at = system.outputs
        stop_at_outputs = not solver.adaptive

        x, next_event, terminate = system.initialize(self.start, stop)
        t = self.t
        i_out = i_bp = 0
        events_here = 0
        if terminate:
            return self._finish(t, x, terminated=True)
        solver.reset(f, t, x)
        z = self._indicators(t, x)
        while True:
            if next_event <= t + eps:
                t = max(t, next_event)      # a time event a rounding error ahead is now
                events_here += 1
                if events_here > MAX_EVENTS_AT_ONE_TIME:
                    raise FmuBuilderError(
                        f"more than {MAX_EVENTS_AT_ONE_TIME} events at t={t:.17g}: the model keeps "
                        "scheduling events without letting time advance; check its time events")
                stats.time_events += 1
                x, next_event, terminate = self._event(t, x, "time")
                if terminate:
                    return self._finish(t, x, terminated=True)
                solver.restart(t, x, keep_step=True)
                z = self._indicators(t, x)
                continue
            i_next = bisect_right(outputs, t + eps, i_out)     # the output times reached
            if i_next > i_out:
                table = outputs_at((t,), x[None, :])
                count, i_out = i_next - i_out, i_next
                record(outputs[i_out - count:i_out], table if count == 1 else np.repeat(table, count, axis=0))
            if t >= stop - eps:
                return self._finish(t, x, terminated=False)

            target = stop if next_event > stop else next_event
            while i_bp < n_bp and breakpoints[i_bp] <= t + eps:
                i_bp += 1
            if i_bp < n_bp and breakpoints[i_bp] < target:
                target = breakpoints[i_bp]
            if stop_at_outputs and i_out < n_out and outputs[i_out] < target:
                target = outputs[i_out]

            t_start = t
            t = solver.step(target)
            x = solver.x
            state_event = False
            if n_z:
                t_end = t
                stats.indicator_evaluations += 1
                t, z, fired, evaluations = cut_at_state_event(
                    self._indicators_on_step, t_start, z, t_end, indicators(t_end, x), eps)
                if fired is not None:
                    stats.indicator_evaluations += evaluations
                    state_event = True
                    if t != t_end:
                        x = solver.interpolate(t)
            i_next = bisect_left(outputs, t - eps, i_out)      # the output times inside the step
            if i_next > i_out:
                times, i_out = outputs[i_out:i_next], i_next
                record(times, outputs_at(np.array(times), solver.interpolate_many(times)))
            events_here = 0

            step_event, terminate = system.completed_step(t, x)
            if terminate:
                return self._finish(t, x, terminated=True)
            if next_event <= t + eps:
                continue    # a time event is due now: the next pass handles it, and any crossing with it
            if state_event or step_event:
                stats.state_events += state_event
                stats.step_events += step_event
                x, next_event, terminate = self._event(t, x, "state" if state_event else "step")
                if terminate:
                    return self._finish(t, x, terminated=True)
                solver.restart(t, x)
                z = self._indicators(t, x)
            elif i_bp < n_bp and t >= breakpoints[i_bp] - eps:
                solver.restart(t, x)        # the inputs' slope changes here

    def _indicators(self, t, x):
        """Indicators at a (re)start, the reference for the next step's sign changes."""
        if not self.system.n_indicators:
            return None
        self.stats.indicator_evaluations += 1
        return self.system.indicators(t, x)

    def _indicators_on_step(self, t):
        """Indicators on the last step's dense output (where a state event is located)."""
        return self.system.indicators(t, self.solver.interpolate(t))

    def _event(self, t, x, kind):
        """Event mode at (t, x), recording the values around it if asked."""
        self.events.append((t, kind))
        if self.record_events:
            self._record_now(t, x)
        x, next_event, terminate = self.system.handle_event(t, x)
        if self.record_events:
            self._record_now(t, x)
        return x, next_event, terminate

    def _record_now(self, t, x) -> None:
        self.recorder.add([t], self.system.outputs(np.array([t]), np.reshape(x, (1, -1))))

    def _finish(self, t, x, terminated: bool) -> None:
        self.t, self.terminated = t, terminated
        if terminated and not self.recorder.has_time(t, self.eps):
            self._record_now(t, x)      # what the model reached
        self.system.terminate()


class _Recorder:
    """Blocks of output rows, turned into typed columns at the end."""

    def __init__(self, names, types):
        self.names, self.types = list(names), list(types)
        self.times: list[float] = []
        self.blocks: list[np.ndarray] = []

    def add(self, times, table: np.ndarray) -> None:
        self.times.extend(times)
        self.blocks.append(table)

    def has_time(self, t: float, eps: float) -> bool:
        return bool(self.times) and abs(self.times[-1] - t) <= eps

    def arrays(self) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        table = np.vstack(self.blocks) if self.blocks else np.zeros((0, len(self.names)))
        values = {}
        for j, (name, kind) in enumerate(zip(self.names, self.types)):
            column = table[:, j].copy()
            if kind == "Integer":
                column = np.rint(column).astype(np.int64)
            elif kind == "Boolean":
                column = column != 0
            values[name] = column
        return np.array(self.times, dtype=float), values


def output_grid(start: float, stop: float, interval: float) -> np.ndarray:
    """start, start + interval, ..., ending exactly at stop."""
    span = stop - start
    eps = 1e-12 * max(abs(start), abs(stop), span)
    count = int(math.floor(span / interval * (1 + 1e-12)))
    grid = start + np.arange(count + 1) * interval
    if stop - grid[-1] > eps:
        grid = np.append(grid, stop)
    else:
        grid[-1] = stop
    return grid
