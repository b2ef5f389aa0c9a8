"""The compiled simulation core: the engine's loop for one FMU instance in C (event_loop.c).

`run(system, solver, ...)` hands an initialised `FmuSystem` and a plan (solver, output grid,
recorded columns, input tables, a correction of the derivatives such as a NeuralFMU's network) to
the C loop and returns what it recorded; nothing runs in Python per step. The C loop is the Python
engine's (engine.py, events.py, solvers.py) operation for operation: with Euler and RK4 on a plain
FMU both give the same numbers to the bit; DOPRI5 and a network sum their products in another order
than numpy, so they agree to round-off. The Python loop stays for systems that change the dynamics
in Python only, and as the reference the tests hold the core to. The library is built with CMake on
first use, once per version of its source, into the build cache (build.cache_dir()), and loaded with
cffi.

`FMUBUILDER_ENGINE=python` in the environment turns the core off (the Python loop everywhere).
"""
from __future__ import annotations

import hashlib
import os
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from cffi import FFI

from ...errors import FmuBuilderError, first_line
from ...fmi import breadcrumb
from ...fmi.binding import ffi as fmi_ffi
from ...fmi.instance import FmuCallError
from ..events import MAX_CUT_STEPS_IN_A_ROW, MAX_EVENTS_AT_ONE_TIME, RELATIVE_TIME_TOLERANCE, time_scale, \
    time_tolerance
from ..solvers import step_size_underflow

SOURCE_DIR = Path(__file__).resolve().parent
SOURCES = ("CMakeLists.txt", "event_loop.c", "event_loop.h", "loop.h", "sensitivity.c")
LIBRARY_NAME = "event_loop.so"
ENGINE_VARIABLE = "FMUBUILDER_ENGINE"

# The FMI functions the loop calls, in the order of event_loop.h's core_call, with the CoreFmu
# field each one fills.
CALLS = (
    ("fmi2SetTime", "set_time"), ("fmi2SetContinuousStates", "set_continuous_states"),
    ("fmi2GetDerivatives", "get_derivatives"), ("fmi2GetEventIndicators", "get_event_indicators"),
    ("fmi2GetContinuousStates", "get_continuous_states"), ("fmi2SetReal", "set_real"),
    ("fmi2GetReal", "get_real"), ("fmi2SetInteger", "set_integer"), ("fmi2GetInteger", "get_integer"),
    ("fmi2SetBoolean", "set_boolean"), ("fmi2GetBoolean", "get_boolean"),
    ("fmi2CompletedIntegratorStep", "completed_integrator_step"), ("fmi2EnterEventMode", "enter_event_mode"),
    ("fmi2EnterContinuousTimeMode", "enter_continuous_time_mode"), ("fmi2NewDiscreteStates", "new_discrete_states"),
)
# The values of event_loop.h's enums.
SOLVERS = {"euler": 0, "rk4": 1, "dopri5": 2}
COLUMN_STATE, COLUMN_DISCRETE, COLUMN_COMPUTED, COLUMN_DERIVATIVE = 0, 1, 2, 3
TYPES = {"Real": 0, "Integer": 1, "Boolean": 2}
SOURCE_STATE, SOURCE_DERIVATIVE, SOURCE_VARIABLE = 0, 1, 2
ACTIVATIONS = {None: 0, "tanh": 1, "sigmoid": 2, "relu": 3}
EVENT_KINDS = ("time", "state", "step")
CORE_FMI_ERROR, CORE_EVENT_STORM, CORE_CHATTERING, CORE_NO_MEMORY, CORE_STEP_UNDERFLOW, CORE_WORK_LIMIT = 1, 2, 3, 4, 5, 6
BASES = ("w", "|w|", "w*|w|", "w^2")      # a base term's forms, in the order of BASIS_*


def enabled() -> bool:
    """Whether the core runs what it can (not with FMUBUILDER_ENGINE=python)."""
    return os.environ.get(ENGINE_VARIABLE, "").strip().lower() != "python"


# What a system may change of FmuSystem and still run in the core: the derivatives and the recorded
# derivative columns, as its compiled_correction() describes them.
_CORRECTED = ("derivatives", "outputs")
_FIXED = ("initialize", "indicators", "completed_step", "handle_event", "terminate", "close")


def applies(system, solver) -> bool:
    """Whether the core runs this system with this solver: an FmuSystem whose derivatives are the
    FMU's or corrected as its `compiled_correction()` describes (a system that changes anything
    else in Python keeps the Python loop), and a solver of solvers.py."""
    from .. import solvers
    from ..system import FmuSystem
    plain_solver = type(solver) in (solvers.Euler, solvers.RK4) or (
        type(solver) is solvers.DOPRI5 and solver.first_step is None)
    if not (enabled() and isinstance(system, FmuSystem) and plain_solver):
        return False
    cls = type(system)
    if any(getattr(cls, name) is not getattr(FmuSystem, name) for name in _FIXED):
        return False
    # The correction must be described by the class that last changed the derivatives, or below it.
    described_by = _owner(cls, "compiled_correction")
    return all(issubclass(described_by, _owner(cls, name)) for name in _CORRECTED)


def _owner(cls, name: str) -> type:
    """The class in cls's method resolution order that defines `name`."""
    return next(klass for klass in cls.__mro__ if name in vars(klass))


class WorkLimitReached(FmuBuilderError):
    """A run stopped at its system's `work_limit` (derivative evaluations)."""


@dataclass
class Correction:
    """A correction of some state derivatives that the core evaluates after each fmi2GetDerivatives
    (see CoreCorrection in event_loop.h): inputs gathered as (SOURCE_*, index), FMU variables read
    by value reference, dense layers (W [rows, cols], b, activation name or None), the corrected
    states with their FMU gates, and a base term: (basis index, input, center, coefficient) grouped
    by basis in BASES order, its bias and gate (0: none)."""
    inputs: list[tuple[int, int]]
    variable_vrs: list[int]
    layers: list[tuple[np.ndarray, np.ndarray, str | None]]
    channels: list[int]
    gate_fmu: np.ndarray
    terms: list[tuple[int, int, float, float]] = field(default_factory=list)
    term_bias: float = 0.0
    term_gate: float = 0.0



@dataclass
class CoreRun:
    """What the C loop recorded: rows of the recorded columns at `times`, the events, counts."""
    times: np.ndarray
    table: np.ndarray
    events: list[tuple[float, str]]
    counts: dict[str, int]
    t: float
    terminated: bool
    x: np.ndarray = field(repr=False)
    next_event: float = float("inf")


def run(system, solver, *, start_time: float, stop_time: float, output_times: np.ndarray, x0: np.ndarray,
        next_event: float, record_events: bool) -> CoreRun:
    """The event loop from the initialised `system` (an FmuSystem standing at start_time with
    states x0 and its next time event) to stop_time, in C."""
    lib, ffi = library()
    plan, keep = _plan(ffi, system, solver, start_time, stop_time, output_times, x0, next_event, record_events)
    fmu = _fmu(ffi, system, plan)
    result = ffi.new("CoreResult *")
    try:
        code = lib.core_run(fmu, plan, result)
        if code:
            _raise(code, result, system)
        return _collected(ffi, result, plan)
    finally:
        lib.core_free_result(result)
        del keep


def run_with_gradient(system, solver, *, start_time: float, stop_time: float, output_times: np.ndarray,
                      x0: np.ndarray, next_event: float, n_parameters: int, weights: np.ndarray | None,
                      record_events: bool = False) -> tuple[CoreRun, np.ndarray, int]:
    """`run` with forward sensitivities to the correction's parameters (core_gradient_run in
    event_loop.h): (the run, the gradient: the sum over the recorded rows and columns of
    weights[row, column] d(value)/dtheta, the events that reset the states). weights [rows,
    columns] for the rows the same run records (events' rows too with record_events), or None:
    the run alone, its resets counted."""
    if solver.adaptive:
        raise ValueError("the core's sensitivities follow the fixed-step solvers (Euler, RK4) only")
    lib, ffi = library()
    plan, keep = _plan(ffi, system, solver, start_time, stop_time, output_times, x0, next_event, record_events)
    fmu = _fmu(ffi, system, plan)
    result = ffi.new("CoreResult *")
    resets = ffi.new("int64_t *")
    gradient = np.zeros(max(n_parameters, 1))
    rows = 0
    if weights is not None:
        weights = np.ascontiguousarray(weights, dtype=np.float64)
        if weights.ndim != 2 or weights.shape[1] != plan.n_columns:
            raise ValueError(f"weights of shape {weights.shape} for rows of {plan.n_columns} columns")
        rows = weights.shape[0]
    pointer = ffi.NULL if weights is None or rows == 0 else ffi.cast("double *", ffi.from_buffer(weights))
    try:
        code = lib.core_gradient_run(fmu, plan, pointer, rows, n_parameters,
                                     ffi.cast("double *", ffi.from_buffer(gradient)), resets, result)
        if code:
            _raise(code, result, system)
        return _collected(ffi, result, plan), gradient[:n_parameters], int(resets[0])
    finally:
        lib.core_free_result(result)
        del keep


# -- the plan --------------------------------------------------------------------------------------

def _plan(ffi, system, solver, start, stop, output_times, x0, next_event, record_events):
    keep = []       # numpy arrays the plan points into, alive until the run returns

    def array(values, c_type="double"):
        """A C pointer into a kept array of `values`."""
        dtype = {"double": np.float64, "int": np.intc, "unsigned int": np.uintc}[c_type]
        data = np.ascontiguousarray(values, dtype=dtype)
        if data.size == 0:
            data = np.zeros(1, dtype=dtype)
        keep.append(data)
        return ffi.cast(f"{c_type} *", ffi.from_buffer(data))
    array.keep = keep.append

    info = system.info
    scale = time_scale(start, stop)
    eps = time_tolerance(start, scale)
    plan = ffi.new("CorePlan *")
    plan.n_states, plan.n_indicators = system.n_states, system.n_indicators
    plan.solver = SOLVERS[solver.name]
    if solver.adaptive:
        plan.rtol, plan.atol, plan.max_step = solver.rtol, solver.atol, solver.max_step
    else:
        plan.step_size = solver.h
    plan.start, plan.stop, plan.time_scale = start, stop, scale
    plan.relative_time_tolerance = RELATIVE_TIME_TOLERANCE
    plan.max_events_at_one_time, plan.max_cuts_in_a_row = MAX_EVENTS_AT_ONE_TIME, MAX_CUT_STEPS_IN_A_ROW
    plan.x0, plan.next_event = array(x0), next_event
    plan.needs_completed_step = not info.capabilities.completed_integrator_step_not_needed
    plan.record_events = bool(record_events)
    plan.max_rhs_evaluations = int(getattr(system, "work_limit", 0) or 0)
    plan.n_outputs, plan.output_times = len(output_times), array(output_times)

    correction = system.compiled_correction()
    if correction is not None:
        plan.correction = _correction(ffi, correction, array)
    derivative_index = {v.name: i for i, v in enumerate(info.derivatives)} if correction is not None else {}
    columns = system.columns
    kinds, indices = [], []
    for var in system.recorded:
        if var.name in derivative_index:
            kinds.append(COLUMN_DERIVATIVE), indices.append(derivative_index[var.name])
        elif var.name in columns.state_index:
            kinds.append(COLUMN_STATE), indices.append(columns.state_index[var.name])
        elif var in columns.discrete:
            kinds.append(COLUMN_DISCRETE), indices.append(columns.discrete.index(var))
        else:
            kinds.append(COLUMN_COMPUTED), indices.append(columns.computed.index(var))
    plan.n_columns = len(kinds)
    plan.column_kind, plan.column_index = array(kinds, "int"), array(indices, "int")
    plan.n_discrete = len(columns.discrete)
    plan.discrete_vrs = array([v.value_reference for v in columns.discrete], "unsigned int")
    plan.discrete_types = array([TYPES[v.api_type] for v in columns.discrete], "int")
    plan.n_computed = len(columns.computed)
    plan.computed_vrs = array([v.value_reference for v in columns.computed], "unsigned int")

    inputs = system.inputs
    if inputs is not None:
        plan.n_samples, plan.sample_times = inputs.time.size, array(inputs.time)
        continuous, slopes, discrete = inputs.tables()
        plan.n_continuous_inputs = len(inputs.continuous)
        plan.continuous_input_vrs = array([v.value_reference for v in inputs.continuous], "unsigned int")
        plan.continuous_values, plan.continuous_slopes = array(continuous), array(slopes)
        breakpoints = [b for b in sorted(system.breakpoints) if start + eps < b < stop - eps]
        plan.n_breakpoints, plan.breakpoints = len(breakpoints), array(breakpoints)
        plan.n_discrete_inputs = len(inputs.discrete)
        plan.discrete_input_vrs = array([v.value_reference for v in inputs.discrete], "unsigned int")
        plan.discrete_input_types = array([TYPES[v.api_type] for v in inputs.discrete], "int")
        plan.discrete_values = array(discrete)
        input_events = system.input_event_times
        plan.n_input_events, plan.input_event_times = len(input_events), array(input_events)
    keep.append(plan)
    return plan, keep


def _correction(ffi, correction: Correction, array):
    c = ffi.new("CoreCorrection *")
    c.n_inputs = len(correction.inputs)
    c.input_source = array([source for source, _ in correction.inputs], "int")
    c.input_index = array([index for _, index in correction.inputs], "int")
    c.n_variables, c.variable_vrs = len(correction.variable_vrs), array(correction.variable_vrs, "unsigned int")
    layers = correction.layers
    c.n_layers = len(layers)
    c.layer_rows = array([W.shape[0] for W, _, _ in layers], "int")
    c.layer_cols = array([W.shape[1] for W, _, _ in layers], "int")
    c.layer_activation = array([ACTIVATIONS[activation] for _, _, activation in layers], "int")
    c.weights = array(np.concatenate([np.ravel(W) for W, _, _ in layers]) if layers else [])
    c.biases = array(np.concatenate([np.ravel(b) for _, b, _ in layers]) if layers else [])
    c.n_channels, c.channel_state = len(correction.channels), array(correction.channels, "int")
    c.gate_fmu = array(correction.gate_fmu)
    terms = correction.terms
    c.n_terms = len(terms)
    c.term_basis = array([t[0] for t in terms], "int")
    c.term_input = array([t[1] for t in terms], "int")
    c.term_center = array([t[2] for t in terms])
    c.term_coefficient = array([t[3] for t in terms])
    c.term_bias, c.term_gate = correction.term_bias, correction.term_gate
    array.keep(c)
    return c


def _fmu(ffi, system, plan):
    """The instance's component and its binary's functions, as the loop calls them."""
    instance = system.instance
    lib = instance.fmu.lib
    fmu = ffi.new("CoreFmu *")
    fmu.component = ffi.cast("void *", int(fmi_ffi.cast("uintptr_t", instance.component)))
    needed = _needed_types(plan)
    for code, (function, name) in enumerate(CALLS):
        pointer = getattr(lib, function, None)
        if pointer is None:
            if any(t in function for t in needed):
                raise FmuBuilderError(f"the FMU's binary does not export {function}, which its variables need")
            continue
        setattr(fmu, name, ffi.cast(ffi.typeof(getattr(fmu, name)), int(fmi_ffi.cast("uintptr_t", pointer))))
        fmu.call_codes[code] = breadcrumb.CODE[function]
    page = breadcrumb.page_address()
    fmu.call_slot = ffi.cast("int64_t *", page + breadcrumb.CALL_SLOT * 8)
    fmu.ping_slot = ffi.cast("int64_t *", page + breadcrumb.PING_SLOT * 8)
    fmu.time_slot = ffi.cast("double *", page + breadcrumb.TIME_OFFSET)
    return fmu


def _needed_types(plan) -> set[str]:
    types = {plan.discrete_types[k] for k in range(plan.n_discrete)}
    types |= {plan.discrete_input_types[k] for k in range(plan.n_discrete_inputs)}
    return {name for name, code in TYPES.items() if code in types}


# -- the result ------------------------------------------------------------------------------------

def _collected(ffi, result, plan) -> CoreRun:
    def doubles(pointer, count):
        return np.frombuffer(ffi.buffer(pointer, count * 8), dtype=np.float64).copy() if count else np.zeros(0)

    rows, width = result.n_rows, plan.n_columns
    table = doubles(result.rows, rows * width).reshape(rows, width)
    n_events = result.n_events
    kinds = np.frombuffer(ffi.buffer(result.event_kinds, n_events * ffi.sizeof("int")), dtype=np.intc) \
        if n_events else np.zeros(0, dtype=np.intc)
    events = list(zip(doubles(result.event_times, n_events).tolist(), (EVENT_KINDS[k] for k in kinds.tolist())))
    counts = {name: int(getattr(result, name)) for name in (
        "steps", "rejected_steps", "rhs_evaluations", "indicator_evaluations", "time_events", "state_events", "step_events",
        "event_iterations")}
    return CoreRun(times=doubles(result.times, rows), table=table, events=events, counts=counts,
                   t=float(result.t), terminated=bool(result.terminated), x=doubles(result.x, plan.n_states),
                   next_event=float(result.next_event))


def _raise(code: int, result, system) -> None:
    """The error the Python loop raises for the same failure."""
    if code == CORE_FMI_ERROR:
        raise FmuCallError(CALLS[result.failed_call][0], result.failed_status, tuple(system.instance.messages))
    t = float(result.error_time)
    if code == CORE_EVENT_STORM:
        raise FmuBuilderError(
            f"more than {MAX_EVENTS_AT_ONE_TIME} events at t={t:.17g}: the model keeps "
            "scheduling events without letting time advance; check its time events")
    if code == CORE_CHATTERING:
        raise FmuBuilderError(
            f"more than {MAX_CUT_STEPS_IN_A_ROW} state events in a row at t={t:.6g} (chattering "
            "or Zeno behaviour); reduce the step size or fix the model")
    if code == CORE_STEP_UNDERFLOW:
        raise step_size_underflow(t, float(result.error_step))
    if code == CORE_WORK_LIMIT:
        raise WorkLimitReached(f"the run needed more than {system.work_limit} derivative evaluations "
                               f"(stopped at t={t:.6g})")
    raise MemoryError("the compiled simulation core ran out of memory")


# -- building and loading the library ----------------------------------------------------------------

_loaded: tuple | None = None


def library():
    """(lib, ffi) of the compiled core, built on first use (cached per source version)."""
    global _loaded
    if _loaded is None:
        ffi = FFI()
        ffi.cdef(_declarations())
        path = _built() / LIBRARY_NAME
        try:
            lib = ffi.dlopen(str(path))
        except OSError as exc:
            raise FmuBuilderError(f"cannot load the compiled simulation core {path} ({first_line(exc)}); "
                                  f"delete that folder to rebuild it") from None
        _loaded = (lib, ffi)
    return _loaded


def _declarations() -> str:
    """event_loop.h as cffi reads it: without preprocessor lines, with CALL_COUNT's value."""
    text = (SOURCE_DIR / "event_loop.h").read_text()
    return "\n".join(line for line in text.splitlines() if not line.lstrip().startswith("#"))


def source_hash() -> str:
    digest = hashlib.sha256()
    for name in SOURCES:
        digest.update(name.encode() + b"\0" + (SOURCE_DIR / name).read_bytes() + b"\0")
    return digest.hexdigest()[:20]


def _built() -> Path:
    from ...build import build_cmake_project, cache_dir, cached_folder

    def fill(staged: Path, scratch: Path) -> None:
        build = build_cmake_project(SOURCE_DIR, scratch / "build")
        shutil.copy2(scratch / "build" / LIBRARY_NAME, staged / LIBRARY_NAME)
        (staged / "build.log").write_text(build.output)
    try:
        return cached_folder(cache_dir() / "event_loop", source_hash(), fill)
    except FmuBuilderError as exc:
        raise FmuBuilderError(f"cannot build fmubuilder's compiled simulation core: {_one_line(exc)}; "
                              f"or set {ENGINE_VARIABLE}=python to simulate with the slower Python loop") from None


def _one_line(exc: Exception) -> str:
    """The message's first line, with the compiler's first error line if the tail holds one."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    compiler = next((line for line in lines[1:] if re.search(r"\berror\b", line, re.IGNORECASE)), None)
    return lines[0] + (f" ({compiler})" if compiler else "")
