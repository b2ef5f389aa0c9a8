"""The hybrid simulation loop: the event sequence of events.py (EventSequence) driven for one
instance with any solver of solvers.py, recording the outputs on the way: the output times reached
(after the events at that time) before each step and at the stop, those inside a step from the
solver's dense output. A fixed-step solver also ends a step at each output time, every solver at
each input kink (a breakpoint, where it restarts). Times within events.time_tolerance are one
instant (docs/ARCHITECTURE.md, "Event handling"). `run` hands every run the compiled core can take
(core.applies) to that loop in C, which is this one written again; the rest runs here.
"""
from __future__ import annotations

import math
import time as wallclock
from bisect import bisect_left, bisect_right

import numpy as np

from . import core
from .events import EventSequence, locate, time_scale, time_tolerance
from .results import SimulationResult, SimulationStats
from .solvers import Solver
from .system import HybridSystem


def run(system: HybridSystem, solver: Solver, *, start_time: float, stop_time: float,
        output_times, record_events: bool = False) -> SimulationResult:
    """Simulate `system` from start_time to stop_time, sampling the outputs at output_times
    (sorted, within [start_time, stop_time]). With record_events the outputs just before
    and after each event are added as extra rows at the event time."""
    started = wallclock.perf_counter()
    if core.applies(system, solver):
        return _run_compiled(system, solver, start_time, stop_time, np.asarray(output_times, dtype=float),
                             record_events, started)
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


def _run_compiled(system, solver, start_time, stop_time, output_times, record_events, started) -> SimulationResult:
    """`run` in the compiled core (core/): the system initialised here, its loop in C."""
    core.library()      # built (or found) before the instance is initialised
    stats = SimulationStats(solver=solver.name)
    recorder = _Recorder(system.output_names, system.output_types)
    x, next_event, terminate = system.initialize(start_time, stop_time)
    eps = time_tolerance(start_time, time_scale(start_time, stop_time))
    if terminate:       # the model stops during its initialisation: what it reached
        recorder.add([start_time], system.outputs((start_time,), x[None, :]))
        system.terminate()
        stats.event_iterations, stats.wall_time = system.event_iterations, wallclock.perf_counter() - started
        time, values = recorder.arrays()
        return SimulationResult(time=time, values=values, stats=stats, terminated_early=start_time < stop_time - eps,
                                stop_time=start_time, events=[])
    done = core.run(system, solver, start_time=start_time, stop_time=stop_time, output_times=output_times,
                    x0=x, next_event=next_event, record_events=record_events)
    system.event_iterations += done.counts.pop("event_iterations")
    system.terminate()
    recorder.add(done.times.tolist(), done.table)
    for key, value in done.counts.items():
        setattr(stats, key, value)
    stats.event_iterations = system.event_iterations
    stats.wall_time = wallclock.perf_counter() - started
    time, values = recorder.arrays()
    return SimulationResult(time=time, values=values, stats=stats,
                            terminated_early=done.terminated and done.t < stop_time - eps,
                            stop_time=done.t, events=done.events)


class _Loop:
    """One simulation run: the event sequence (events.EventSequence) driven for one instance with
    `solver`, recording the outputs on the way."""

    def __init__(self, system, solver, start_time, stop_time, output_times, recorder, stats, record_events):
        self.system, self.solver = system, solver
        self.start, self.stop = float(start_time), float(stop_time)
        self.scale = time_scale(self.start, self.stop)
        self.eps = time_tolerance(self.start, self.scale)       # at every time of the experiment
        self.outputs = output_times.tolist()
        self.i_out, self.n_out = 0, len(self.outputs)
        self.recorder, self.stats, self.record_events = recorder, stats, record_events
        self.breakpoints = [float(b) for b in sorted(system.breakpoints)
                            if self.start + self.eps < b < self.stop - self.eps]
        self.i_bp = 0
        if not self.breakpoints:
            self.stepped_on = None      # nothing to do after a step without an event
        self.stop_at_outputs = not solver.adaptive
        self.events: list[tuple[float, str]] = []
        self.terminated = False
        self.t = self.start
        self.indicator_evaluations = 0
        # what each step calls, bound once
        self._solver_step, self._indicators_at = solver.step, system.indicators
        self._system_completed_step = system.completed_step

    def run(self) -> None:
        x, next_event, terminate = self.system.initialize(self.start, self.stop)
        if terminate:
            return self._finish(self.start, x, terminated=True)
        self.x = x
        self.solver.reset(self.system.derivatives, self.start, x)
        counts = {"time_events": 0, "state_events": 0, "step_events": 0}
        seq = EventSequence(self.start, next_event, self._indicators(self.start, x), counts, self.scale)
        try:
            seq.drive(self.stop, self)
        finally:
            self.stats.indicator_evaluations = self.indicator_evaluations
        for key, value in counts.items():
            setattr(self.stats, key, value)
        if not seq.terminated:
            self._record_reached(seq.t)
        self._finish(seq.t, self.x, seq.terminated)

    # -- what the sequence asks of its driver (see EventSequence) ------------------------------
    def step_limit(self, seq, stop):
        """The stop, the next input kink, the next output time for a fixed-step solver (once the
        output times reached are recorded: the sequence asks before each step)."""
        t, target = seq.t, stop
        if self.i_out < self.n_out and self.outputs[self.i_out] <= t + self.eps:
            self._record_reached(t)
        i_out, outputs = self.i_out, self.outputs
        if self.breakpoints:
            breakpoints, i_bp = self.breakpoints, self.i_bp
            while i_bp < len(breakpoints) and breakpoints[i_bp] <= t + self.eps:
                i_bp += 1
            self.i_bp = i_bp
            if i_bp < len(breakpoints) and breakpoints[i_bp] < target:
                target = breakpoints[i_bp]
        if self.stop_at_outputs and i_out < self.n_out and outputs[i_out] < target:
            target = outputs[i_out]
        return target

    def step(self, seq, end):
        t = self._solver_step(end)
        self.x = self.solver.x
        return t

    def indicators_at_end(self, seq, t):
        self.indicator_evaluations += 1
        return self._indicators_at(t, self.x)

    def cut_at_state_event(self, seq, t0, t1, z1, tolerance):
        t, z, _, evaluations = locate(self._indicators_on_step, t0, seq.z, t1, z1, tolerance)
        self.indicator_evaluations += evaluations
        if t != t1:
            self.x = self.solver.interpolate(t)
        return t, z

    def completed_step(self, seq, state_event):
        t, i_out = seq.t, self.i_out
        if i_out < self.n_out and self.outputs[i_out] < t - self.eps:     # output times inside the step
            i_next = bisect_left(self.outputs, t - self.eps, i_out)
            times, self.i_out = self.outputs[i_out:i_next], i_next
            self.recorder.add(times, self.system.outputs(np.array(times), self.solver.interpolate_many(times)))
        return self._system_completed_step(t, self.x)

    def stepped_on(self, seq):
        if self.i_bp < len(self.breakpoints) and seq.t >= self.breakpoints[self.i_bp] - self.eps:
            self.solver.restart(seq.t, self.x)        # the inputs' slope changes here

    def event(self, seq, kind):
        """Event mode at the sequence's point, recording the values around it if asked; the solver
        restarts on the states it left (a time event keeps the solver's step size)."""
        t = seq.t
        self.events.append((t, kind))
        if self.record_events:
            self._record_now(t, self.x)
        self.x, seq.next_event, seq.terminated = self.system.handle_event(t, self.x)
        if self.record_events:
            self._record_now(t, self.x)
        if not seq.terminated:
            self.solver.restart(t, self.x, keep_step=kind == "time")
            if seq.z is not None:       # the indicators after the event: the next step's reference
                self.indicator_evaluations += 1
                seq.z = self._indicators_at(t, self.x)

    # ------------------------------------------------------------------------------------------
    def _record_reached(self, t) -> None:
        """The output times reached (after the events at that time)."""
        i_next = bisect_right(self.outputs, t + self.eps, self.i_out)
        if i_next > self.i_out:
            table = self.system.outputs((t,), self.x[None, :])
            count, self.i_out = i_next - self.i_out, i_next
            self.recorder.add(self.outputs[self.i_out - count:self.i_out],
                              table if count == 1 else np.repeat(table, count, axis=0))

    def _indicators(self, t, x):
        """Indicators at the start, the reference for the first step's sign changes."""
        if not self.system.n_indicators:
            return None
        self.indicator_evaluations += 1
        return self.system.indicators(t, x)

    def _indicators_on_step(self, t):
        """Indicators on the last step's dense output (where a state event is located)."""
        return self.system.indicators(t, self.solver.interpolate(t))

    def _record_now(self, t, x) -> None:
        self.recorder.add([t], self.system.outputs((t,), np.reshape(x, (1, -1))))

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
    eps = time_tolerance(start, time_scale(start, stop))
    count = int(math.floor(span / interval * (1 + 1e-12)))
    grid = start + np.arange(count + 1) * interval
    if stop - grid[-1] > eps:
        grid = np.append(grid, stop)
    else:
        grid[-1] = stop
    return grid
