"""Runs of the declared model, plain or with an added term in one state derivative.

An :class:`AddedTerm` is ``coefficient * basis(w - center)`` added to ``der(x_c)``, where
``w`` is a state, an FMU variable or the time. :class:`TermSystem`, the engine's
:class:`~fmubuilder.simulation.FmuSystem` with the terms added inside the closed loop (in the
compiled core where the terms allow: :class:`CompiledTermSystem`), makes a controller in the model
react to them as it would to the real effect.

:class:`ModelRunner` simulates over the data window and returns what the sensors would
have logged: the measured signals filtered by the bench's sensor lag and sampled at the
data's time stamps, plus the trajectories of the variables the diagnosis looks at.
"""
from __future__ import annotations

import math
import time as wallclock
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..errors import FmuBuilderError
from ..fmi.instance import Fmu
from ..simulation.core import BASES as CORE_BASES, SOURCE_STATE, SOURCE_VARIABLE, Correction, WorkLimitReached
from ..simulation.engine import output_grid, run
from ..simulation.inputs import input_signals_from
from ..simulation.results import sample_settled
from ..simulation.solvers import make_solver
from ..simulation.system import FmuSystem
from ..data import sensor_reading

TIME = "time"  # pseudo-variable: a term in the time since the start of the window

# Basis forms phi(u) of a centered variable u = w - center: odd and even, linear and quadratic.
BASES = {
    "1": lambda u: 1.0,
    "w": lambda u: u,
    "|w|": abs,
    "w*|w|": lambda u: u * abs(u),
    "w^2": lambda u: u * u,
}


def basis_values(basis: str, u: np.ndarray) -> np.ndarray:
    """phi(u) for an array (the scalar forms above work on arrays too; the constant needs its shape)."""
    return np.ones_like(u) if basis == "1" else np.asarray(BASES[basis](u), dtype=float)


@dataclass(frozen=True)
class AddedTerm:
    channel: int          # index of the state whose derivative gets the term
    variable: str         # FMU variable name or TIME
    basis: str            # key of BASES
    center: float         # value of the variable at the window start
    coefficient: float

    def form(self) -> str:
        """phi(w - center) as text, e.g. 'speed*|speed|' or '(temperature - 293.15)^2'."""
        return form_text(self.variable, self.basis, self.center)

    def expression(self, digits: int = 4) -> str:
        """coefficient * form, e.g. '-0.0003 * speed*|speed|'."""
        if self.basis == "1":
            return f"{self.coefficient:.{digits}g}"
        return f"{self.coefficient:.{digits}g} * {self.form()}"


def form_text(variable: str, basis: str, center: float) -> str:
    if basis == "1":
        return "1"
    u = _centered_text(variable, center)
    atom = u if " " not in u else f"({u})"
    return {"w": atom, "|w|": f"|{u}|", "w*|w|": f"{atom}*|{u}|", "w^2": f"{atom}^2"}[basis]


def _centered_text(variable: str, center: float) -> str:
    if center == 0.0:
        return variable
    sign = "-" if center > 0 else "+"
    return f"{variable} {sign} {abs(center):.6g}"


class TrialTooSlow(FmuBuilderError):
    """A run with an added term takes far longer than the plain model (the term made the
    model stiff or chattering); the caller abandons or shrinks the term."""


class TermSystem(FmuSystem):
    """An FmuSystem whose derivatives get the added terms, in the Python loop (CompiledTermSystem:
    in the core). `max_calls` derivative evaluations end a run with TrialTooSlow (the core counts
    its solver's), `deadline` (a perf_counter() time) in the Python loop only."""

    def __init__(self, fmu: Fmu, terms: Sequence[AddedTerm], start_time: float, deadline: float = math.inf,
                 max_calls: float = math.inf, **system):
        super().__init__(fmu, **system)
        self.terms = list(terms)
        self._start_time = start_time   # a time term's origin
        self.work_limit = int(max_calls) if math.isfinite(max_calls) else 0
        self._deadline = deadline     # perf_counter() time after which the run is abandoned (a cap only)
        self._max_calls = max_calls   # derivative evaluations after which the run is abandoned
        self._calls = 0
        info = self.info
        self._state_index = state_index = {v.name: i for i, v in enumerate(info.states)}
        self._readers = []
        for term in self.terms:
            if term.variable == TIME or term.variable in state_index:
                self._readers.append(state_index.get(term.variable))
            else:
                self._readers.append(self.instance.real_getter([info.variable(term.variable).value_reference]))

    def derivatives(self, t: float, x: np.ndarray) -> np.ndarray:
        self._calls += 1
        if self._calls > self._max_calls:
            raise TrialTooSlow(f"a run with the added term {self.terms[0].expression()} exceeded its work limit")
        if self._calls % 256 == 0 and wallclock.perf_counter() > self._deadline:
            raise TrialTooSlow(f"a run with the added term {self.terms[0].expression()} exceeded the time budget")
        dx = super().derivatives(t, x)          # the FMU is now at (t, x)
        for term, reader in zip(self.terms, self._readers):
            if term.variable == TIME:
                w = t - self._start_time
            elif isinstance(reader, int):
                w = x[reader]
            else:
                w = reader()[0]
            dx[term.channel] += term.coefficient * BASES[term.basis](w - term.center)
        return dx


class CompiledTermSystem(TermSystem):
    """A TermSystem whose terms the compiled core adds, as the base term of its correction: terms
    on one derivative, none in the time but a constant (`compiles`)."""

    @staticmethod
    def compiles(terms: Sequence[AddedTerm]) -> bool:
        return (len({term.channel for term in terms}) == 1
                and all(term.variable != TIME or term.basis == "1" for term in terms))

    def compiled_correction(self) -> Correction:
        info, state_index = self.info, self._state_index
        inputs, variables, terms, bias = [], [], [], 0.0
        for term in self.terms:
            if term.basis == "1":
                bias += term.coefficient
                continue
            if term.variable in state_index:
                inputs.append((SOURCE_STATE, state_index[term.variable]))
            else:
                inputs.append((SOURCE_VARIABLE, len(variables)))
                variables.append(info.variable(term.variable).value_reference)
            terms.append((CORE_BASES.index(term.basis), len(inputs) - 1, term.center, term.coefficient))
        return Correction(inputs=inputs, variable_vrs=variables, layers=[], channels=[self.terms[0].channel],
                          gate_fmu=np.ones(1), terms=sorted(terms, key=lambda t: t[0]), term_bias=bias, term_gate=1.0)


@dataclass
class ModelRun:
    """What one simulation gives the diagnosis."""
    predicted: dict[str, np.ndarray]     # measured signals as the sensors would log them, at the data times
    trajectories: dict[str, np.ndarray]  # recorded variables at the data times (no sensor lag)
    wall_time: float
    derivative_calls: int = 0            # the solver's derivative evaluations: the run's work


class ModelRunner:
    """Simulates the declared model over [start, stop] for the data's time stamps."""

    def __init__(self, fmu_path, *, start_values: dict, data_time: np.ndarray, start: float, stop: float,
                 measured: Sequence[str], recorded: Sequence[str], sensor_lag: float = 0.0,
                 fine_step: float | None = None, rtol: float = 1e-6, inputs: dict | None = None):
        self.fmu = Fmu(fmu_path)
        self.info = self.fmu.info
        # The data's FMU input columns ({name: values at data_time}) drive every run, as in every
        # other stage: without them a model driven by inputs shows its own mistake as the residual.
        self.inputs = (input_signals_from({"time": np.asarray(data_time, dtype=float), **inputs}, self.info)
                       if inputs else None)
        self.start_values = dict(start_values)
        self.start, self.stop = float(start), float(stop)
        self.data_time = data_time[(data_time >= self.start) & (data_time <= self.stop)]
        self.measured = list(measured)
        self.recorded = list(dict.fromkeys([*self.measured, *recorded]))
        self.sensor_lag = float(sensor_lag)
        self.rtol = rtol
        # Measured outputs equal to a state derivative (name -> channels): a term added to
        # that derivative is added to the output too.
        self.output_aliases: dict[str, list[int]] = {}
        if self.sensor_lag > 0:
            step = fine_step or min(0.01, self.sensor_lag / 5, float(np.median(np.diff(data_time))) / 4)
            self.grid = output_grid(self.start, self.stop, step)
        else:
            self.grid = self.data_time
        self.runs = 0
        self.total_wall_time = 0.0

    def close(self) -> None:
        self.fmu.close()

    def simulate(self, terms: Sequence[AddedTerm] = (), *, trajectories: bool = True,
                 time_limit: float = math.inf, max_calls: float = math.inf) -> ModelRun:
        """One run; without `trajectories` only the measured signals are recorded (faster).
        A run with terms that needs more than `max_calls` derivative evaluations, or takes
        longer than `time_limit` seconds, raises TrialTooSlow."""
        started = wallclock.perf_counter()
        recorded = self.recorded if trajectories else self.measured
        if terms and self.output_aliases:   # the terms' variables, to add them to aliased outputs
            recorded = list(dict.fromkeys([*recorded, *(t.variable for t in terms if t.variable != TIME)]))
        settings = dict(variables=recorded, start_values=self.start_values, inputs=self.inputs, tolerance=self.rtol)
        with_terms = CompiledTermSystem if CompiledTermSystem.compiles(terms) else TermSystem
        system = (with_terms(self.fmu, terms, self.start, started + time_limit, max_calls, **settings) if terms
                  else FmuSystem(self.fmu, **settings))
        solver = make_solver("dopri5", rtol=self.rtol, atol=1e-9, max_step=(self.stop - self.start) / 50)
        try:
            # A trial term can drive the model far off (overflow, NaN); the trial's score says so.
            with np.errstate(all="ignore"):
                result = run(system, solver, start_time=self.start, stop_time=self.stop, output_times=self.grid,
                             record_events=self.sensor_lag > 0)
        except WorkLimitReached:
            raise TrialTooSlow(f"a run with the added term {terms[0].expression()} exceeded its work limit") from None
        finally:
            system.close()
        predicted, sampled = {}, {}
        for name in recorded:
            values = np.asarray(result[name], dtype=float)
            values = values + self._aliased_terms(name, terms, result)
            sampled[name] = sample_settled(result.time, values, self.data_time)
            if name in self.measured:
                predicted[name] = sensor_reading(result.time, values, self.data_time, self.sensor_lag)
        wall = wallclock.perf_counter() - started
        self.runs += 1
        self.total_wall_time += wall
        return ModelRun(predicted=predicted, trajectories=sampled, wall_time=wall,
                        derivative_calls=int(result.stats.rhs_evaluations))

    def _aliased_terms(self, name: str, terms: Sequence[AddedTerm], result) -> np.ndarray | float:
        """The terms added to the derivatives an output equals (see output_aliases)."""
        total = 0.0
        for term in terms:
            if term.channel in self.output_aliases.get(name, ()):
                if term.variable == TIME:
                    w = result.time - self.start
                else:
                    w = np.asarray(result[term.variable], dtype=float)
                total = total + term.coefficient * basis_values(term.basis, w - term.center)
        return total


def rms(values: np.ndarray) -> float:
    values = np.asarray(values, dtype=float)
    return math.sqrt(float(np.mean(values * values))) if values.size else 0.0
