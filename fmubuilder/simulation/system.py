"""What the simulation loop drives: a hybrid system with continuous states, event
indicators and discrete events, behind a small protocol.

`FmuSystem` implements it for one FMI 2.0 Model-Exchange instance. A system that changes
the dynamics (a NeuralFMU adds a network's output to some derivatives) wraps or subclasses
it and overrides `derivatives`; the loop in engine.py stays the same.

Every method that takes (t, x) puts the FMU at that time and state first (cheap C calls),
so callers never track which point the FMU was last evaluated at.
"""
from __future__ import annotations

import bisect
import math
from functools import partial
from typing import Protocol, Sequence

import numpy as np

from ..errors import FmuBuilderError
from ..fmi.instance import EventInfo, Fmu, FmuCallError, convert_value
from ..fmi.model import Variable
from .events import event_mode
from .inputs import InputSignals


class HybridSystem(Protocol):
    """The protocol the engine needs (see FmuSystem for the FMI meaning of each call)."""

    n_states: int
    n_indicators: int
    output_names: list[str]
    output_types: list[str]         # 'Real', 'Integer' or 'Boolean' per output column
    breakpoints: Sequence[float]    # times where the right-hand side has a kink
    event_iterations: int           # discrete-state update passes so far

    def initialize(self, start_time: float, stop_time: float) -> tuple[np.ndarray, float, bool]:
        """Set up and initialise; returns (x0, next_time_event or inf, terminate)."""

    def derivatives(self, t: float, x: np.ndarray) -> np.ndarray:
        """dx/dt at (t, x); may reuse one buffer between calls (solvers copy it)."""

    def indicators(self, t: float, x: np.ndarray) -> np.ndarray:
        """Event indicators at (t, x), as a new array (the engine keeps it for a step)."""

    def completed_step(self, t: float, x: np.ndarray) -> tuple[bool, bool]:
        """After an accepted step ending at (t, x): (step_event, terminate)."""

    def handle_event(self, t: float, x: np.ndarray) -> tuple[np.ndarray, float, bool]:
        """Process an event at (t, x): (x after the event, next_time_event or inf, terminate)."""

    def outputs(self, times: np.ndarray, states: np.ndarray) -> np.ndarray:
        """Values of the recorded variables (columns, in output_names order) at several
        points (rows): times has shape (k,), states (k, n_states)."""

    def terminate(self) -> None: ...

    def close(self) -> None: ...


class FmuSystem:
    """An FMI 2.0 Model-Exchange instance as a HybridSystem.

    `start_values` (name -> value, strings allowed) are set before initialisation; `inputs`
    drive input variables over time; `variables` are the names recorded by `outputs`.
    """

    def __init__(self, fmu: Fmu, *, variables: Sequence[str], start_values: dict | None = None,
                 inputs: InputSignals | None = None, tolerance: float | None = None, logging: bool = False):
        self.info = info = fmu.info
        self.n_states = info.n_states
        self.n_indicators = info.n_event_indicators
        self.tolerance = tolerance
        self.start_values = _checked_start_values(info, start_values or {})
        recorded = [info.variable(name) for name in variables]
        for var in recorded:
            if var.api_type == "String":
                raise FmuBuilderError(f"cannot record String variable '{var.name}'; choose numeric variables")
        self.recorded = recorded
        self.output_names = [v.name for v in recorded]
        self.output_types = [v.api_type for v in recorded]
        self.inputs = inputs
        self.breakpoints = inputs.breakpoints if inputs is not None else np.zeros(0)
        self.input_event_times = inputs.discrete_change_times().tolist() if inputs is not None else []
        self.event_iterations = 0
        self._continuous_mode = False
        self._terminated = False

        self.instance = fmu.instantiate(logging=logging)
        inst = self.instance
        self._set_time = inst.set_time
        self._set_x = inst.set_continuous_states
        self._get_dx = inst.get_derivatives
        self._get_z = inst.get_event_indicators
        self._completed = inst.completed_integrator_step
        self._needs_completed_step = not info.capabilities.completed_integrator_step_not_needed
        self._set_inputs = None
        if inputs is not None and inputs.continuous:
            self._set_inputs = inst.real_setter([v.value_reference for v in inputs.continuous])
        self.columns = _OutputColumns(inst, info, recorded)

    def compiled_correction(self):
        """How a subclass corrects the derivatives, as the compiled core (core.Correction) evaluates
        it; None: the FMU's own. A subclass that overrides `derivatives` without it runs in Python."""
        return None

    # -- life cycle ------------------------------------------------------------------------
    def initialize(self, start_time: float, stop_time: float) -> tuple[np.ndarray, float, bool]:
        inst = self.instance
        inst.setup_experiment(start_time, stop_time, self.tolerance)
        for name, value in self.start_values.items():
            try:
                inst.set({name: value})
            except FmuCallError as exc:
                raise FmuBuilderError(f"the FMU rejected the start value {name}={value!r} ({exc})") from None
        inst.enter_initialization_mode()
        self._apply_inputs(start_time)
        inst.exit_initialization_mode()
        self.columns.discrete_changed()
        return self._after_event(start_time, event_mode(inst, entered=True))

    def terminate(self) -> None:
        if not self._terminated:
            self._terminated = True
            self._continuous_mode = False
            self.instance.terminate()

    def close(self) -> None:
        self.instance.free()

    # -- continuous time (hot path) ----------------------------------------------------------
    def _at(self, t: float, x: np.ndarray) -> None:
        self._set_time(t)
        if self._set_inputs is not None:
            self._set_inputs(self.inputs.at(t))
        self._set_x(x)

    def derivatives(self, t: float, x: np.ndarray) -> np.ndarray:
        self._set_time(t)           # _at, inlined: this is the innermost call of a simulation
        if self._set_inputs is not None:
            self._set_inputs(self.inputs.at(t))
        self._set_x(x)
        return self._get_dx()

    def indicators(self, t: float, x: np.ndarray) -> np.ndarray:
        self._at(t, x)
        return self._get_z()

    def completed_step(self, t: float, x: np.ndarray) -> tuple[bool, bool]:
        if not self._needs_completed_step:
            return False, False
        self._at(t, x)
        return self._completed(True)

    def outputs(self, times: np.ndarray, states: np.ndarray) -> np.ndarray:
        columns = self.columns
        if len(times) == 1:
            return self._output_row(times[0], states[0])[None, :]
        # Many points (dense output within a step): the states' and discrete values' columns whole.
        parts = [states]
        if columns.n_discrete:
            parts.append(columns.discrete_values()[None, :].repeat(len(times), axis=0))
        if columns.n_computed:
            computed, read = np.empty((len(times), columns.n_computed)), columns.read_computed
            for row, t in enumerate(times):
                if self._continuous_mode:       # in event mode the FMU already holds (t, x)
                    self._at(t, states[row])
                computed[row] = read()
            parts.append(computed)
        # The parts side by side are [all states | discrete | computed]; order picks the columns.
        table = np.concatenate(parts, axis=1) if len(parts) > 1 else np.array(states, dtype=float)
        return table if columns.in_order(table.shape[1]) else table.take(columns.order, axis=1)

    def _output_row(self, t: float, x: np.ndarray) -> np.ndarray:
        """outputs() of one point, written into one row: [states | discrete | computed] in the
        recorded columns' order."""
        columns = self.columns
        n, n_discrete = self.n_states, columns.n_discrete
        row = np.empty(n + n_discrete + columns.n_computed)
        row[:n] = x
        if n_discrete:
            row[n:n + n_discrete] = columns.discrete_values()
        if columns.n_computed:
            if self._continuous_mode:       # in event mode the FMU already holds (t, x)
                self._at(t, x)
            row[n + n_discrete:] = columns.read_computed()
        return row if columns.in_order(row.size) else row.take(columns.order)

    # -- events ------------------------------------------------------------------------------
    def handle_event(self, t: float, x: np.ndarray) -> tuple[np.ndarray, float, bool]:
        self._at(t, x)
        self._continuous_mode = False
        self.columns.discrete_changed()
        inputs = self.inputs     # _at has set the continuous ones; discrete ones change in event mode
        discrete = inputs is not None and inputs.discrete
        info = event_mode(self.instance, before_iteration=(lambda: self.instance.set(inputs.discrete_at(t)))
                          if discrete else None)
        return self._after_event(t, info)

    def _after_event(self, t: float, info: EventInfo) -> tuple[np.ndarray, float, bool]:
        self.event_iterations += info.iterations
        # Re-read the states: the event may have reset them (valuesOfContinuousStatesChanged).
        states = self.instance.get_continuous_states()
        if info.terminate_simulation:
            return states, math.inf, True
        self._continuous_mode = True
        return states, self._next_time_event(info.next_event_time_or_inf, t), False

    def _next_time_event(self, fmu_next: float, t: float) -> float:
        """The FMU's next time event or the next change of a discrete input, if earlier."""
        i = bisect.bisect_right(self.input_event_times, t)
        return min(fmu_next, self.input_event_times[i]) if i < len(self.input_event_times) else fmu_next

    def _apply_inputs(self, t: float) -> None:
        if self.inputs is None:
            return
        if self._set_inputs is not None:
            self._set_inputs(self.inputs.at(t))
        if self.inputs.discrete:
            self.instance.set(self.inputs.discrete_at(t))


class _OutputColumns:
    """How each recorded variable is read, cheapest first: states straight from x;
    variables that change only at events (discrete, parameters) once per event; the rest
    (continuous, computed from the state) from the FMU at each sample."""

    def __init__(self, inst, info, recorded: list[Variable]):
        self.state_index = state_index = {v.name: i for i, v in enumerate(info.states)}
        self.discrete = discrete = [v for v in recorded if v.name not in state_index and v.variability != "continuous"]
        self.computed = computed = [v for v in recorded if v.name not in state_index and v.variability == "continuous"]
        self.n_discrete, self.n_computed = len(discrete), len(computed)
        # Column of each recorded variable in [states | discrete | computed].
        position = {v.name: len(state_index) + k for k, v in enumerate(discrete + computed)}
        position.update(state_index)
        self.order = np.array([position[v.name] for v in recorded], dtype=int)
        self._natural = self.order.tolist() == list(range(len(self.order)))
        self.read_computed = inst.real_getter([v.value_reference for v in computed])
        self._read_discrete = values_reader(inst, discrete)
        self._discrete = None

    def in_order(self, width: int) -> bool:
        """Whether [states | discrete | computed] is already the recorded columns' order."""
        return self._natural and width == len(self.order)

    def discrete_changed(self) -> None:
        self._discrete = None

    def discrete_values(self) -> np.ndarray:
        if self._discrete is None:
            self._discrete = self._read_discrete()
        return self._discrete


def values_reader(instance, variables: list[Variable]):
    """A function giving the current values of Real, Integer and Boolean `variables` as one float64
    array, each type read in one call."""
    parts = []
    for api_type in ("Real", "Integer", "Boolean"):
        positions = [k for k, v in enumerate(variables) if v.api_type == api_type]
        if positions:
            vrs = [variables[k].value_reference for k in positions]
            get = instance.real_getter(vrs) if api_type == "Real" else partial(
                getattr(instance, f"get_{api_type.lower()}"), vrs)
            parts.append((np.array(positions, dtype=int), get))

    def read() -> np.ndarray:
        values = np.empty(len(variables))
        for positions, get in parts:
            values[positions] = get()
        return values
    return read


def _checked_start_values(info, start_values: dict) -> dict:
    """Start values converted to their variables' types; unknown or unsettable names fail."""
    if not isinstance(start_values, dict):
        raise FmuBuilderError("start values must be a mapping of variable names to values, e.g. {'g': 9.81}")
    checked = {}
    for name, value in start_values.items():
        var = info.variable(str(name))
        if not _settable_before_initialization(var):
            raise FmuBuilderError(
                f"cannot set a start value for '{var.name}': it is a {var.variability} {var.causality} "
                f"the model computes (initial='{var.initial or 'calculated'}'); set a parameter, input "
                "or a variable with initial='exact' or 'approx' instead")
        converted = convert_value(var, value)
        if var.api_type == "Real" and not math.isfinite(converted):
            raise FmuBuilderError(f"start value of {var.name} must be a finite number, got {value!r}")
        checked[var.name] = converted
    return checked


def _settable_before_initialization(var: Variable) -> bool:
    if var.variability == "constant" or var.causality in ("calculatedParameter", "independent"):
        return False
    return var.causality in ("parameter", "input") or var.initial in ("exact", "approx")
