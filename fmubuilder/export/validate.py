"""Round-trip validation of an exported hybrid FMU.

The hybrid FMU (wrapper C code + generated network kernel + original binary) is simulated by
fmpy and compared with the Python reference (original FMU + onnxruntime, reference.py):

* fmpy Euler vs the reference under fmpy's Euler semantics (`simulate_fmpy_euler`): fmpy steps
  exactly one output interval at a time, shortens a step only to land on a time event,
  checks event indicators at the end of each step (no root location: the event is handled
  at the step end) and compares against the indicators of its previous check, which it does
  not refresh after an event. Reproducing that loop step for step makes the two runs
  evaluate the same arithmetic, so they agree to round-off (target: relative 1e-9);
* the engine's Euler on the hybrid FMU vs on the reference with identical settings (the same
  loop on both sides, with the engine's own event location; target: relative 1e-9);
* the engine's DOPRI5 on the hybrid FMU vs on the reference with identical settings (target:
  relative 1e-9: the step control sees the same numbers up to round-off). Informational only
  when the model had step events: they happen at the end of an adaptive step, and round-off
  in the error estimate can shift the step ends;
* fmpy CVode vs the engine's DOPRI5 on the reference, both at `rtol`: different solvers, so
  they agree only within their global errors, far above the local tolerance over a run with
  events (fmpy's CVode about 1e3 * rtol on the bouncing ball, DOPRI5 about 10 * rtol): target
  `cross_solver_tolerance`. Both sample at half the output interval, and the samples within a
  quarter output interval of one of the reference's events are dropped (a sample at an event
  instant may be taken before or after it): even a time event at every output point leaves the
  midway samples. Informational only with step events (fmpy calls fmi2CompletedIntegratorStep
  only at its communication points, the engine after every internal step) or inputs (fmpy
  updates continuous inputs only at communication points).

"Relative" differences are normalised per signal by max(1e-3, largest |value| of the
reference), so signals crossing zero do not blow the ratio up. A row with no samples left to
compare says "not compared" and does not pass. fmpy's modelDescription validation is part of the
report.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import tempfile
import zipfile
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Sequence

import numpy as np

from fmubuilder.errors import FmuBuilderError
from fmubuilder.progress import counted

from .spec import HybridSpec

FIXED_STEP_TOLERANCE = 1e-9
ADAPTIVE_TOLERANCE_FACTOR = 1e4
DEFAULT_RTOL = 1e-10
_SCALE_FLOOR = 1e-3
# Cross-solver samples closer than this many output intervals to an event are not compared.
EVENT_WINDOW = 0.25


@dataclass
class SignalDifference:
    name: str
    max_abs: float
    max_rel: float


@dataclass
class Comparison:
    """One pair of simulations compared on a common time grid."""

    label: str           # e.g. "fmpy Euler vs reference (fmpy Euler semantics)"
    tolerance: float     # allowed max relative difference
    signals: list[SignalDifference] = field(default_factory=list)
    error: str | None = None   # a simulation failed
    informational: str | None = None   # why this row does not count towards the verdict
    samples: int = 0           # time points compared (after dropping those near events)

    @property
    def compared(self) -> bool:
        return self.error is None and self.samples > 0 and bool(self.signals)

    @property
    def max_rel(self) -> float:
        return max((s.max_rel for s in self.signals), default=math.nan) if self.compared else math.nan

    @property
    def passed(self) -> bool:
        return self.compared and self.max_rel <= self.tolerance

    @property
    def verdict(self) -> str:
        if self.error is None and not self.compared:
            return "not compared (no samples left)"
        if self.informational:
            return f"{'within' if self.passed else 'outside'} tolerance, informational only: {self.informational}"
        return "passed" if self.passed else "FAILED"


@dataclass
class ValidationReport:
    hybrid_fmu: Path
    fmpy_problems: list[str]
    comparisons: list[Comparison]

    @property
    def passed(self) -> bool:
        return not self.fmpy_problems and all(c.passed for c in self.comparisons if not c.informational)

    def comparison(self, label_start: str) -> Comparison:
        return next(c for c in self.comparisons if c.label.startswith(label_start))

    def format_table(self) -> str:
        lines = [f"validation of {self.hybrid_fmu}", "fmpy modelDescription validation: "
                 + ("passed" if not self.fmpy_problems else "FAILED: " + "; ".join(self.fmpy_problems))]
        for comparison in self.comparisons:
            lines.append(f"\n{comparison.label}: {comparison.verdict} (tolerance {comparison.tolerance:.0e} relative"
                         f"{f', {comparison.samples} samples' if comparison.compared else ''})")
            if comparison.error:
                lines.append(f"  error: {comparison.error}")
            if not comparison.compared:     # a failed simulation included
                continue
            width = max([len("signal")] + [len(s.name) for s in comparison.signals])
            lines.append(f"  {'signal':<{width}}  {'max abs diff':>12}  {'max rel diff':>12}")
            for s in comparison.signals:
                lines.append(f"  {s.name:<{width}}  {s.max_abs:12.3e}  {s.max_rel:12.3e}")
        lines.append(f"\nround trip: {'passed' if self.passed else 'FAILED'}")
        return "\n".join(lines)


def validate_hybrid(hybrid_fmu: str | os.PathLike, spec: HybridSpec | str | os.PathLike | None = None,
                    data_csv: str | os.PathLike | None = None, start_values: dict | None = None, *,
                    stop_time: float | None = None, step_size: float | None = None,
                    rtol: float = DEFAULT_RTOL) -> ValidationReport:
    """Simulate the hybrid FMU with fmpy and the engine and compare with the Python reference.

    `spec` (a HybridSpec or its JSON path) defaults to the copy embedded in the FMU at export.
    `data_csv` gives the FMU's inputs over time (columns: time, then input names; others are
    ignored) and the time span. `start_values` apply to both sides; the hybrid's gate
    parameters (e.g. "hybrid.v.p_ann") are allowed and set the reference's gates.
    """
    from fmpy.validation import validate_fmu
    from fmubuilder.fmi import read_model_info

    hybrid_fmu = Path(hybrid_fmu)
    hybrid_info = read_model_info(hybrid_fmu)
    problems = validate_fmu(str(hybrid_fmu))
    with contextlib.ExitStack() as stack:
        if spec is None:
            spec, gate_names = _embedded_spec(hybrid_fmu, Path(stack.enter_context(tempfile.TemporaryDirectory())))
        else:
            spec = spec if isinstance(spec, HybridSpec) else HybridSpec.load(spec)
            gate_names = _gate_names_of(spec)
        original_info = read_model_info(spec.original_fmu)
        spec.check(original_info)
        setup = _Setup.make(hybrid_info, original_info, spec, gate_names, data_csv, start_values or {},
                            stop_time, step_size, rtol)
        between = dataclasses.replace(setup, step=setup.step / 2)   # adds the midpoints of the output grid
        rows = [
            partial(_compare, "fmpy Euler vs reference (fmpy Euler semantics)", FIXED_STEP_TOLERANCE,
                     lambda: _fmpy_run(hybrid_fmu, setup, "Euler"),
                     lambda: _reference_run(spec, setup, "fmpy-euler"), setup.signals),
            partial(_compare, "engine Euler: hybrid FMU vs reference", FIXED_STEP_TOLERANCE,
                     lambda: _engine_fmu_run(hybrid_fmu, setup, "euler"),
                     lambda: _reference_run(spec, setup, "euler"), setup.signals),
            partial(_compare, f"engine DOPRI5 (rtol {rtol:g}): hybrid FMU vs reference", FIXED_STEP_TOLERANCE,
                     lambda: _engine_fmu_run(hybrid_fmu, setup, "dopri5"),
                     lambda: _reference_run(spec, setup, "dopri5"), setup.signals,
                     informational=_step_event_caveat),
            partial(_compare, f"fmpy CVode vs engine DOPRI5 on reference (rtol {rtol:g}, samples between events)",
                     lambda run: cross_solver_tolerance(rtol, len(run.events)),
                     lambda: _fmpy_run(hybrid_fmu, between, "CVode"),
                     lambda: _reference_run(spec, between, "dopri5"), setup.signals,
                     event_window=EVENT_WINDOW * setup.step,
                     informational=lambda run: _cross_solver_caveat(setup, run)),
        ]
        comparisons = [row() for row in counted(rows, "validation: round-trip comparisons", "row")]
    return ValidationReport(hybrid_fmu=hybrid_fmu, fmpy_problems=list(problems), comparisons=comparisons)


# -- what to simulate -------------------------------------------------------------------------

@dataclass
class _Setup:
    start: float
    stop: float
    step: float
    rtol: float
    signals: list[str]            # compared: outputs, states, channel derivatives
    fmu_start_values: dict        # for the original's variables (both sides)
    p_ann: list[float]
    p_fmu: list[float]
    gate_start_values: dict       # for the hybrid FMU
    input_data: dict | None       # {'time': ..., name: ...} with the FMU inputs only

    @classmethod
    def make(cls, hybrid_info, original_info, spec, gate_names, data_csv, start_values, stop_time, step_size, rtol):
        experiment = hybrid_info.default_experiment
        start = experiment.start_time if experiment.start_time is not None else 0.0
        stop = experiment.stop_time if experiment.stop_time is not None else start + 1.0
        input_data = None
        if data_csv is not None:
            input_data = _read_inputs(data_csv, original_info)
            start, stop = float(input_data["time"][0]), float(input_data["time"][-1])
        if stop_time is not None:
            stop = float(stop_time)
        if not stop > start:
            raise FmuBuilderError(f"stop time {stop:g} is not after start time {start:g}; give a later stop time")
        step = float(step_size) if step_size else (experiment.step_size or (stop - start) / 500)
        if not step > 0:
            raise FmuBuilderError(f"step size {step:g} must be positive")
        p_ann, p_fmu = list(spec.p_ann), list(spec.p_fmu)
        fmu_values, gate_values = {}, {}
        for name, value in start_values.items():
            if name in gate_names:
                c, which = gate_names[name]
                (p_ann if which == "p_ann" else p_fmu)[c] = float(value)
                gate_values[name] = float(value)
            else:
                original_info.variable(name)  # unknown names fail here with a suggestion
                fmu_values[name] = value
        signals = [v.name for v in original_info.outputs if v.type != "String"]
        signals += [s.name for s in original_info.states if s.name not in signals]
        signals += [c for c in spec.channels if c not in signals]
        return cls(start, stop, step, rtol, signals, fmu_values, p_ann, p_fmu, gate_values, input_data)


def _read_inputs(data_csv, info) -> dict:
    from fmubuilder.simulation.inputs import read_csv_signals
    time, columns = read_csv_signals(data_csv)
    names = {v.name for v in info.inputs}
    return {"time": time, **{name: values for name, values in columns.items() if name in names}}


def _gate_names_of(spec: HybridSpec) -> dict[str, tuple[int, str]]:
    """The gates as the export names them (see _gate_index)."""
    from .hybrid_description import channel_layouts
    return _gate_index((layout.p_ann, layout.p_fmu) for layout in channel_layouts(spec))


def _embedded_spec(hybrid_fmu: Path, folder: Path) -> tuple[HybridSpec, dict[str, tuple[int, str]]]:
    """The spec stored in the FMU at export, with the original FMU rebuilt in `folder`."""
    from fmubuilder.fmi.archive import binary_platform
    from .wrapper import EMBEDDED_DIR, EMBEDDED_ONNX, EMBEDDED_ORIGINAL_XML, EMBEDDED_SPEC

    prefix = f"resources/{EMBEDDED_DIR}/"
    with zipfile.ZipFile(hybrid_fmu) as hybrid:
        names = set(hybrid.namelist())
        if prefix + EMBEDDED_SPEC not in names:
            raise FmuBuilderError(
                f"{hybrid_fmu} holds no hybrid spec (not exported by fmubuilder); pass the spec with --against")
        data = json.loads(hybrid.read(prefix + EMBEDDED_SPEC))
        original_xml = hybrid.read(prefix + EMBEDDED_ORIGINAL_XML)
        if prefix + EMBEDDED_ONNX in names:     # a hybrid of overrides alone has no network
            (folder / EMBEDDED_ONNX).write_bytes(hybrid.read(prefix + EMBEDDED_ONNX))
        identifier = _model_identifier(original_xml)
        # The original's binaries folder (its library and the files beside it) sits in resources/.
        binaries = set(data.get("original_binaries", [f"{identifier}.so"]))
        original = folder / "original.fmu"
        with zipfile.ZipFile(original, "w", zipfile.ZIP_DEFLATED) as out:
            out.writestr("modelDescription.xml", original_xml)
            for name in sorted(binaries):
                out.writestr(f"binaries/{binary_platform()}/{name}", hybrid.read(f"resources/{name}"))
            for name in names:
                if name.startswith("resources/") and not name.endswith("/") and not name.startswith(prefix) \
                        and name.removeprefix("resources/") not in binaries:
                    out.writestr(name, hybrid.read(name))
    spec = HybridSpec.from_dict(data, folder, f"{hybrid_fmu}'s embedded spec")
    return spec, _gate_index((entry["p_ann"], entry["p_fmu"]) for entry in data.get("gates", []))


def _gate_index(gates) -> dict[str, tuple[int, str]]:
    """Gate parameter name -> (channel index, 'p_ann' | 'p_fmu'), from each channel's (p_ann, p_fmu) names."""
    index = {}
    for c, (p_ann, p_fmu) in enumerate(gates):
        index[p_ann], index[p_fmu] = (c, "p_ann"), (c, "p_fmu")
    return index


def _model_identifier(xml: bytes) -> str:
    from lxml import etree
    me = etree.fromstring(xml).find("ModelExchange")
    if me is None or not me.get("modelIdentifier"):
        raise FmuBuilderError("the embedded original modelDescription.xml has no ModelExchange element")
    return me.get("modelIdentifier")


# -- runs -------------------------------------------------------------------------------------

@dataclass
class _Run:
    time: np.ndarray
    values: dict[str, np.ndarray]
    events: list[tuple[float, str]] = field(default_factory=list)   # (time, kind); engine runs only


def _fmpy_run(hybrid_fmu: Path, setup: _Setup, solver: str) -> _Run:
    start_values = {**setup.fmu_start_values, **setup.gate_start_values}
    kwargs = dict(start_time=setup.start, stop_time=setup.stop, solver=solver, output=setup.signals,
                  start_values=start_values, record_events=False, validate=False, output_interval=setup.step)
    if solver == "Euler":
        kwargs["step_size"] = setup.step    # fmpy's Euler takes one step per output interval
    else:
        kwargs["relative_tolerance"] = setup.rtol
    if setup.input_data is not None:
        kwargs["input"] = _structured(setup.input_data)
    result = simulate_with_fmpy(hybrid_fmu, **kwargs)
    return _Run(np.asarray(result["time"], dtype=float),
                {name: np.asarray(result[name], dtype=float) for name in setup.signals})


def simulate_with_fmpy(fmu: Path, **kwargs):
    """fmpy.simulate_fmu on the FMU as fmi.archive extracts it (what running needs, capped),
    removed however the run ends: fmpy removes its own extraction only after a run that returns
    (an FMU that fails a call left one in the temporary folder each time)."""
    import fmpy

    from fmubuilder.fmi.archive import FmuArchive
    archive = FmuArchive(fmu)
    try:
        return fmpy.simulate_fmu(str(archive.directory), **kwargs)
    finally:
        archive.close()


def _structured(data: dict) -> np.ndarray:
    names = list(data)
    array = np.zeros(len(data["time"]), dtype=[(n, np.float64) for n in names])
    for name in names:
        array[name] = data[name]
    return array


def _engine_fmu_run(hybrid_fmu: Path, setup: _Setup, solver: str) -> _Run:
    from fmubuilder.fmi.instance import Fmu
    from fmubuilder.simulation import FmuSystem
    with Fmu(hybrid_fmu) as fmu:
        system = FmuSystem(fmu, variables=setup.signals, start_values={**setup.fmu_start_values,
                                                                        **setup.gate_start_values},
                           inputs=_engine_inputs(setup, fmu.info))
        return _engine_run(system, setup, solver)


def _reference_run(spec: HybridSpec, setup: _Setup, solver: str) -> _Run:
    from fmubuilder.fmi.instance import Fmu
    from .reference import HybridReference
    with Fmu(spec.original_fmu) as fmu:
        # The overrides as start values of the original; the hybrid sets them itself.
        system = HybridReference(fmu, spec, variables=setup.signals,
                                 start_values={**spec.overrides, **setup.fmu_start_values},
                                 inputs=_engine_inputs(setup, fmu.info), p_ann=setup.p_ann, p_fmu=setup.p_fmu,
                                 tolerance=setup.rtol if solver == "dopri5" else None)
        if solver == "fmpy-euler":
            try:
                return simulate_fmpy_euler(system, setup.start, setup.stop, setup.step)
            finally:
                system.close()
        return _engine_run(system, setup, solver)


def _engine_inputs(setup: _Setup, info):
    if setup.input_data is None:
        return None
    from fmubuilder.simulation import input_signals_from
    return input_signals_from(dict(setup.input_data), info)


def _engine_run(system, setup: _Setup, solver: str) -> _Run:
    from fmubuilder.simulation import make_solver, output_grid, run
    if solver == "euler":
        integrator = make_solver("euler", step_size=setup.step)
    else:
        integrator = make_solver("dopri5", rtol=setup.rtol, atol=setup.rtol * 1e-2,
                                 max_step=(setup.stop - setup.start) / 50)
    try:
        result = run(system, integrator, start_time=setup.start, stop_time=setup.stop,
                     output_times=output_grid(setup.start, setup.stop, setup.step))
    finally:
        system.close()
    return _Run(result.time, {name: np.asarray(result[name], dtype=float) for name in setup.signals},
                list(result.events))


def simulate_fmpy_euler(system, start: float, stop: float, step: float) -> _Run:
    """fmpy's Model-Exchange loop with its ForwardEuler solver (fmpy/simulation.py), over a
    HybridSystem, without inputs events and event recording: see the module docstring."""
    x, next_event, terminate = system.initialize(start, stop)
    t = start
    z = system.indicators(t, x) if system.n_indicators else np.zeros(0)
    times, rows = [], []
    n_steps = 0
    next_regular = t
    while not terminate:
        if math.isclose(t, next_regular):
            times.append(t)
            rows.append(system.outputs(np.array([t]), np.reshape(x, (1, -1)))[0])
        if t > stop or math.isclose(t, stop):
            break
        next_regular = start + (n_steps + 1) * step
        target = next_regular
        if math.isfinite(next_event) and target > next_event and not math.isclose(target, next_event):
            target = next_event
        if target > stop and not math.isclose(target, stop):
            target = stop
        time_event = math.isfinite(next_event) and math.isclose(target, next_event)
        dx = system.derivatives(t, x)
        x = x + (target - t) * dx
        # fmpy reads the indicators after setting the states, before it sets the new time.
        z_previous, z = z, (system.indicators(t, x) if system.n_indicators else z)
        state_event = bool(np.any(((z_previous < 0) & (z >= 0)) | ((z_previous > 0) & (z <= 0))))
        t = target
        if math.isclose(t, next_regular):
            n_steps += 1
        step_event, terminate = system.completed_step(t, x)
        if terminate:
            break
        if time_event or state_event or step_event:
            x, next_event, terminate = system.handle_event(t, x)
    system.terminate()
    table = np.vstack(rows) if rows else np.zeros((0, len(system.output_names)))
    return _Run(np.array(times), {name: table[:, j] for j, name in enumerate(system.output_names)})


# -- comparison -------------------------------------------------------------------------------

def _step_event_caveat(reference: _Run) -> str | None:
    if any(kind == "step" for _, kind in reference.events):
        return ("the model has step events, handled at the end of an adaptive step, whose size "
                "round-off differences can shift")
    return None


def cross_solver_tolerance(rtol: float, events: int) -> float:
    """Two adaptive solvers restart at every event, and each restart adds a global error of the
    order of the local tolerance with its own sign: the difference grows like a random walk,
    with the square root of the number of events (a sampled controller at 100 Hz gives
    thousands of them)."""
    return ADAPTIVE_TOLERANCE_FACTOR * rtol * math.sqrt(max(1, events))


def _cross_solver_caveat(setup: _Setup, reference: _Run) -> str | None:
    if any(kind == "step" for _, kind in reference.events):
        return "the model has step events, which fmpy and the engine handle at different times"
    if setup.input_data is not None:
        return "fmpy updates continuous inputs only at communication points"
    return None


def _compare(label: str, tolerance, run_hybrid, run_reference, signals: Sequence[str],
             event_window: float | None = None, informational=None) -> Comparison:
    """Run both sides and compare them on their common grid; with `event_window`, the samples
    within that many seconds of one of the reference's events are left out. `tolerance` is a
    number, or a function of the reference run that gives it."""
    comparison = Comparison(label=label, tolerance=tolerance if not callable(tolerance) else math.nan)
    try:
        hybrid = run_hybrid()
        reference = run_reference()
    except Exception as exc:  # a failed simulation is a failed comparison, reported in the table
        comparison.error = f"{type(exc).__name__}: {exc}"
        return comparison
    if callable(tolerance):
        comparison.tolerance = tolerance(reference)
    if informational is not None:
        comparison.informational = informational(reference)
    # When the model terminates, the engine records the instant it reached and fmpy does not:
    # one extra final sample on one side is expected, anything else is a mismatch.
    n = min(hybrid.time.size, reference.time.size)
    atol = 1e-9 * max(1.0, abs(float(reference.time[-1]))) if reference.time.size else 0.0
    if n == 0 or abs(hybrid.time.size - reference.time.size) > 1 or \
            not np.allclose(hybrid.time[:n], reference.time[:n], rtol=0, atol=atol):
        comparison.error = (f"the time grids differ ({hybrid.time.size} vs {reference.time.size} samples, "
                            f"ending at {hybrid.time[-1]:g} vs {reference.time[-1]:g})")
        return comparison
    keep = np.ones(n, dtype=bool)
    if event_window is not None and reference.events:
        keep = _away_from_events(reference.time[:n], [t for t, _ in reference.events], event_window)
    comparison.samples = int(np.count_nonzero(keep))
    if comparison.samples == 0:
        return comparison
    for name in signals:
        a, b = hybrid.values[name][:n][keep], reference.values[name][:n][keep]
        difference = np.abs(a - b)
        max_abs = float(np.max(difference))
        if np.any(np.isnan(a) != np.isnan(b)):
            max_abs = math.inf
        scale = max(_SCALE_FLOOR, float(np.nanmax(np.abs(b))) if b.size else 0.0)
        comparison.signals.append(SignalDifference(name, max_abs, max_abs / scale))
    return comparison


def _away_from_events(time: np.ndarray, events: Sequence[float], window: float) -> np.ndarray:
    """Mask of the times farther than `window` from every event time."""
    events = np.unique(np.asarray(events, dtype=float))
    right = np.clip(np.searchsorted(events, time), 0, events.size - 1)
    left = np.clip(right - 1, 0, events.size - 1)
    nearest = np.minimum(np.abs(time - events[left]), np.abs(time - events[right]))
    return nearest > window
