"""Simulate an FMI 2.0 Model-Exchange FMU: solvers, event handling, inputs, results.

    from fmubuilder.simulation import simulate
    result = simulate("model.fmu", stop_time=3.0, rtol=1e-8)
    result["h"], result.stats, result.to_csv("out.csv")
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

from ..errors import FmuBuilderError
from ..fmi.instance import Fmu
from .engine import output_grid, run
from .inputs import InputSignals, input_signals_from, load_input_csv, read_csv_signals
from .results import SimulationResult, SimulationStats
from .solvers import DOPRI5, RK4, Euler, Solver, integrate, make_solver
from .system import FmuSystem, HybridSystem

__all__ = ["simulate", "run", "SimulationResult", "SimulationStats", "FmuSystem", "HybridSystem",
           "Solver", "Euler", "RK4", "DOPRI5", "make_solver", "integrate", "read_csv_signals",
           "InputSignals", "load_input_csv", "input_signals_from", "output_grid"]

# Outputs per run beyond which the output interval is surely a mistake.
MAX_OUTPUT_ROWS = 10_000_000


def simulate(fmu_path: str | Path, *, start_time: float | None = None, stop_time: float | None = None,
             start_values: dict | None = None, input_csv: str | Path | None = None, inputs=None,
             variables: Sequence[str] | None = None, solver: str = "dopri5", rtol: float = 1e-6,
             atol: float = 1e-8, step_size: float | None = None, output_interval: float | None = None,
             record_events: bool = False, logging: bool = False) -> SimulationResult:
    """Simulate an FMU from start_time to stop_time and sample its variables.

    start/stop time default to the FMU's DefaultExperiment (else 0 and start + 1);
    start_values: {name: value} set before initialisation (strings are converted);
    input_csv or inputs ({'time': [...], name: [...]}): FMU inputs over time;
    variables: names to record (default: outputs, then states);
    solver: 'dopri5' (adaptive; rtol/atol), 'euler' or 'rk4' (fixed step_size, default the
    DefaultExperiment stepSize, else the output interval); for 'dopri5', step_size caps
    the step (default (stop - start) / 50);
    output_interval: sampling period (default the DefaultExperiment stepSize, else
    (stop - start) / 500); record_events adds rows just before and after each event.
    """
    with Fmu(fmu_path) as fmu:
        info = fmu.info
        experiment = info.default_experiment
        start = _number("start_time", start_time, _given(experiment.start_time, 0.0))
        stop = _number("stop_time", stop_time, _given(experiment.stop_time, start + 1.0))
        if not stop > start:
            raise FmuBuilderError(f"stop time {stop:g} is not after start time {start:g}; give a later stop time")
        interval = _positive("output_interval", output_interval,
                             experiment.step_size if experiment.step_size else (stop - start) / 500)
        if (stop - start) / interval > MAX_OUTPUT_ROWS:
            raise FmuBuilderError(
                f"output interval {interval:g} would record over {MAX_OUTPUT_ROWS} rows; choose a larger interval")
        step = None if step_size is None else _positive("step_size", step_size, None)
        integrator = _make_solver(solver, rtol, atol, step, experiment.step_size or interval, stop - start)
        signals = _inputs(input_csv, inputs, info)
        names = list(variables) if variables is not None else _default_variables(info)
        if not names:
            raise FmuBuilderError("no variables to record: give at least one name in variables")
        system = FmuSystem(fmu, variables=names, start_values=start_values, inputs=signals,
                           tolerance=integrator.rtol if integrator.adaptive else None, logging=logging)
        try:
            return run(system, integrator, start_time=start, stop_time=stop,
                       output_times=output_grid(start, stop, interval), record_events=record_events)
        finally:
            system.close()


def _given(value, default):
    return default if value is None else value


def _number(label: str, value, default: float) -> float:
    if value is None:
        return float(default)
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise FmuBuilderError(f"{label} must be a number, got {value!r}") from None
    if not math.isfinite(number):
        raise FmuBuilderError(f"{label} must be a finite number, got {value!r}")
    return number


def _positive(label: str, value, default) -> float:
    number = _number(label, value, default)
    if not number > 0:
        raise FmuBuilderError(f"{label} must be positive, got {value!r}")
    return number


def _make_solver(name, rtol, atol, step, default_step, span) -> Solver:
    key = str(name).lower()
    rtol = _number("rtol", rtol, 1e-6)
    atol = _number("atol", atol, 1e-8)
    if key == "dopri5":
        return make_solver(key, rtol=rtol, atol=atol, max_step=step if step is not None else span / 50)
    return make_solver(key, step_size=step if step is not None else default_step)


def _inputs(input_csv, inputs, info) -> InputSignals | None:
    if input_csv is not None and inputs is not None:
        raise FmuBuilderError("give the inputs either as a CSV file or in memory, not both")
    if input_csv is not None:
        return load_input_csv(input_csv, info)
    return input_signals_from(inputs, info) if inputs is not None else None


def _default_variables(info) -> list[str]:
    """Outputs, then states; String outputs have no column in a numeric result."""
    names = [v.name for v in info.outputs if v.api_type != "String"]
    names += [v.name for v in info.states if v.name not in names]
    return names
