"""The FMU as a differentiable layer, and the FMU-side work the differentiable solver does at events.

`FmuEvaluator` drives B instances of one FMU side by side (one per batch element): it sets time,
inputs and continuous states, reads the state derivatives and a chosen list of Real variables
(outputs, locals), and - only when a gradient is wanted - their Jacobian with respect to the
continuous states x and to chosen tunable parameters p:

* from fmi2GetDirectionalDerivative when the FMU provides it (one call per column), probed once and
  replaced by finite differences if the FMU rejects a requested unknown/known pair;
* otherwise by forward finite differences: perturb one state with fmi2SetContinuousStates by a
  step scaled to max(|x_i|, nominal_i), read again, restore.

`fmu_call` wraps this in a torch.autograd.Function: the Jacobian is computed in the forward pass
(the FMU's discrete state has moved on by the time backward runs); `JacobianSparsity` skips the
columns known to be zero.

At events `FmuEvaluator.handle_event` runs the FMU's own event iteration and, when asked, its
linearisation (`EventOutcome`; the design: solve.py's docstring, item 3). `EventSensitivity`
perturbs the knowns seen to matter one by one and probes the others together.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from ..errors import FmuBuilderError
from ..fmi import FmuCallError, FmuInstance, ModelInfo
from ..simulation.events import event_mode

# Relative step of the one-sided finite differences (about sqrt of the float64 resolution).
FD_RELATIVE_STEP = 1e-7
# How far a shadow that has not crossed at a state event is pushed across: up to 2^10 steps.
MAX_PUSH_DOUBLINGS = 10


def fd_steps(x: np.ndarray, nominal: np.ndarray) -> np.ndarray:
    """Perturbation per state: relative to the state's magnitude or its nominal value."""
    return FD_RELATIVE_STEP * np.maximum(np.abs(x), nominal)


@dataclass
class EventOutcome:
    """What one event (or the initialization) did to one batch element, and its linearisation.

    With q tracked discrete states d (`FmuEvaluator.q`), the solver propagates a zero-valued
    gradient carrier dd [q] per element:  dd+ = B (x-, p)-deviation + A dd,  x+ = x+_value +
    R (x-, p)-deviation + Rd dd,  and every FMU evaluation until the next event adds G dd+.
    In the memoryless fallback (no discrete state observable) dd has width n+k, B is the matrix M
    of the design notes in solve.py, A is zero and G the identity (all None here)."""
    x_plus: np.ndarray           # continuous state after the event
    values_changed: bool         # the FMU reset continuous states
    next_event_time: float       # inf when no time event is scheduled
    terminate: bool
    R: np.ndarray | None = None  # [n, n+P]  d x+ / d(x-, p); None when the states were not reset
    Rd: np.ndarray | None = None  # [n, q]   d x+ / d d-
    B: np.ndarray | None = None  # [q, n+P]  d d+ / d(x-, p)
    A: np.ndarray | None = None  # [q, q]    d d+ / d d-
    G: np.ndarray | None = None  # [n+k, q]  d(derivatives, variables) / d d+


class JacobianSparsity:
    """Which columns (continuous states) of the Jacobian d(unknowns)/dx can be non-zero.

    The FMU's ModelStructure declares the states each derivative and output depends on; a column
    no unknown depends on is skipped. Where some unknown declares nothing (no `dependencies`
    attribute, or a local variable), any column may be non-zero: the columns not yet seen non-zero
    are then probed together at every evaluation, by one perturbation of all of them at once with
    distinct weights (`probe_weights`); if it changes anything, they are computed one by one and
    those found non-zero join the computed columns for good. A column is thus skipped only where
    the FMU declares it zero or where it is zero at that very point, never on an earlier guess."""

    def __init__(self, info: ModelInfo, unknowns: Sequence[str]):
        n = info.n_states
        declared = [info.dependencies.get(name) for name in unknowns]
        self.complete = all(deps is not None for deps in declared)
        index = {v.name: i for i, v in enumerate(info.states)}
        self.computed = np.zeros(n, dtype=bool)
        for deps in declared:
            if deps is None:
                continue
            self.computed[[index[d] for d in deps if d in index]] = True
        self.probe_weights = _probe_weights(n)
        self._index()

    def _index(self) -> None:
        """The column lists, kept between changes: they are asked for at every FMU evaluation.
        `columns` are computed one by one, `unchecked` probed together (none when the
        ModelStructure declares every unknown), with their `unchecked_weights`."""
        self.columns = np.flatnonzero(self.computed)
        self.unchecked = np.zeros(0, dtype=int) if self.complete else np.flatnonzero(~self.computed)
        self.unchecked_weights = self.probe_weights[self.unchecked]

    def found(self, columns: np.ndarray) -> None:
        self.computed[columns] = True
        self._index()

    @property
    def skipped(self) -> list[int]:
        return np.flatnonzero(~self.computed).tolist()


def _probe_weights(count: int) -> np.ndarray:
    """Distinct weights in [1, 2) for a combined perturbation (golden-ratio sequence), so that the
    effects of several knowns do not cancel exactly."""
    return 1.0 + np.modf(np.arange(1, count + 1) * 0.6180339887498949)[0]


class EventSensitivity:
    """Per-event perturbation bookkeeping, shared by all elements and kept across runs.

    A column (known) is non-trivial when its perturbation changed the discrete states, the
    derivatives or variables, or the reset map beyond identity. The columns non-trivial at the
    previous event are perturbed one by one; the others are probed together by one combined
    perturbation (distinct weights), and perturbed one by one only where the probe shows an
    effect, so a known that acts only at some events (a relay switching) is never missed.
    Shadows (discrete states with memory, see solve.py) are kept while any propagated shadow has
    shown an effect, during the first `warmup` events, around every `recheck`-th, and (for an FMU
    with `state_events`) until shadows have been propagated through a state event: a held sample
    (the VLDM's driver error) shows memory only there (dropped before, its gradient was 0.4 % off
    over 10 s of driving, 1.4 % over 40 s; benchmarks/bench_gradient.py)."""

    def __init__(self, n_knowns: int, warmup: int = 4, recheck: int = 500, state_events: bool = True):
        self.n_knowns, self.warmup, self.recheck = n_knowns, warmup, recheck
        self.state_event_checked = not state_events   # shadows went through a state event
        self.recent = np.zeros(n_knowns, dtype=bool)   # non-trivial at the previous event
        self.seen = np.zeros(n_knowns, dtype=bool)     # ever non-trivial
        self.uses = 0
        self.probe_weights = _probe_weights(n_knowns)
        self.memory_seen = False
        self.start_run()
        self._index()

    def _index(self) -> None:
        """The column lists of the next event, kept until an event changes them."""
        self._columns = np.flatnonzero(self.recent)
        self._unchecked = np.flatnonzero(~self.recent)

    def keep_shadows(self) -> bool:
        return (self.memory_seen or not self.state_event_checked or self.uses < self.warmup + 1
                or self.uses % self.recheck >= self.recheck - 1)

    def start_run(self) -> None:
        self.perturbations = self.propagations = self._run_events = 0
        self.seconds = 0.0

    def columns(self) -> np.ndarray:
        """The knowns perturbed one by one."""
        return self._columns

    def unchecked(self) -> np.ndarray:
        """The knowns probed together."""
        return self._unchecked

    @property
    def skipped(self) -> list[int]:
        return np.flatnonzero(~self.seen).tolist()

    def observe(self, columns: np.ndarray, nonzero: np.ndarray, probes: int) -> None:
        self.uses += 1
        self.recent[:] = False
        self.recent[columns[nonzero]] = True
        self._index()
        self.seen |= self.recent
        self._run_events += 1
        self.perturbations += len(columns) + probes

    def stats(self) -> dict:
        events = max(self._run_events, 1)
        return {"events": self._run_events, "perturbations": self.perturbations,
                "shadow_propagations": self.propagations,
                "event_iterations_per_event": (self.perturbations + self.propagations) / events,
                "seconds": self.seconds, "skipped_columns": self.skipped, "memory": self.memory_seen}


class _Candidates:
    """Perturbed post-event FMU states of one element and one event: their discrete-state
    deviations, output deviations and reset deviations, with optional snapshots (shadows)."""

    def __init__(self):
        self.dd, self.df, self.dx, self.handles = [], [], [], []

    def add(self, dd, df, dx, handle):
        self.dd.append(dd)
        self.df.append(df)
        self.dx.append(dx)
        self.handles.append(handle)


class FmuEvaluator:
    """B instances of one FMU, evaluated side by side (see the module docstring).

    Rows of the returned arrays are [derivatives (n) | variables (k)].
    """

    def __init__(self, instances: Sequence[FmuInstance], info: ModelInfo, variables: Sequence[str] = (),
                 inputs: Sequence[str] = (), parameters: Sequence[str] = (), jacobian: str = "auto"):
        self.instances = list(instances)
        self.info = info
        self.n = info.n_states
        self.nz = info.n_event_indicators
        self.variables = list(variables)
        self.k = len(self.variables)
        self.inputs = list(inputs)
        self.parameters = list(parameters)
        self.P = len(self.parameters)
        for name in self.variables + self.inputs + self.parameters:
            var = info.variable(name)
            if var.type != "Real":
                raise FmuBuilderError(f"'{name}' is a {var.type} variable; only Real variables can feed a NeuralFMU")
            if name in self.inputs and (var.causality != "input" or var.variability != "continuous"):
                raise FmuBuilderError(f"'{name}' is not a continuous Real input of {info.model_name}; "
                                      "a NeuralFMU takes only continuous Real inputs from data")
            if name in self.parameters and not (var.is_parameter and var.variability == "tunable"):
                raise FmuBuilderError(
                    f"'{name}' is not a tunable parameter of {info.model_name}; only tunable parameters can be trained")
        self.state_vrs = [v.value_reference for v in info.states]
        self.unknown_vrs = [v.value_reference for v in info.derivatives] + \
                           [info.variable(name).value_reference for name in self.variables]
        self.input_vrs = [info.variable(name).value_reference for name in self.inputs]
        self.param_vrs = [info.variable(name).value_reference for name in self.parameters]
        self._readers = [inst.real_reader([info.variable(v).value_reference for v in self.variables])
                         for inst in self.instances]
        self._input_setters = [inst.real_setter(self.input_vrs) for inst in self.instances]
        self.nominal = np.ones(self.n)
        self.can_snapshot = info.capabilities.can_get_and_set_fmu_state
        if jacobian not in ("auto", "directional", "fd"):
            raise FmuBuilderError(f"unknown jacobian method '{jacobian}': use auto, directional or fd")
        provides = info.capabilities.provides_directional_derivative
        if jacobian == "directional" and not provides:
            raise FmuBuilderError(f"{info.model_name} provides no directional derivatives; use jacobian='fd'")
        self._directional_x = self._directional_p = provides and jacobian != "fd"
        self._param_mode: str | None = None  # how the CT-mode parameter columns are found (probed)
        self.sparsity = JacobianSparsity(info, [v.name for v in info.derivatives] + self.variables)
        # The observable part of the FMU's discrete state: Real locals and outputs changed at events only.
        self.discrete = [v.name for v in info.variables.values()
                         if v.type == "Real" and v.variability == "discrete" and v.causality in ("local", "output")]
        self.q = len(self.discrete)
        self._d_getters = [inst.real_getter([info.variable(v).value_reference for v in self.discrete])
                           for inst in self.instances]
        B = len(self.instances)
        self._pre = [None] * B   # FMU-state snapshots, reused in place
        self._post = [None] * B
        self._here = [None] * B  # the nominal state while the shadows are read between events
        self._shadows: list[list] = [[] for _ in range(B)]     # (snapshot, discrete deviation) per element
        self._pools: list[list[list]] = [[[], []] for _ in range(B)]  # two alternating snapshot pools
        self._turn = [0] * B
        self.n_evaluations = 0
        self.n_jacobian_columns = 0

    @property
    def width(self) -> int:
        return self.n + self.k

    @property
    def carrier_width(self) -> int:
        """Width of the discrete-state gradient carrier dd (see EventOutcome)."""
        return self.q if self.q else self.width

    def refresh_nominals(self) -> None:
        if self.n:
            nominal = np.abs(self.instances[0].get_nominals_of_continuous_states())
            self.nominal = np.where(nominal > 0, nominal, 1.0)

    def free(self) -> None:
        """Release the snapshots (the instances belong to the caller)."""
        for b, inst in enumerate(self.instances):
            handles = [self._pre[b], self._post[b], self._here[b]] + self._pools[b][0] + self._pools[b][1]
            for handle in handles:
                if handle is not None:
                    inst.free_fmu_state(handle)
            self._pre[b] = self._post[b] = self._here[b] = None
            self._pools[b] = [[], []]
            self._shadows[b] = []

    def forget_shadows(self, b: int) -> None:
        self._shadows[b] = []

    # -- evaluation --------------------------------------------------------------------------
    def set_point(self, b: int, t: float, x: np.ndarray, u: np.ndarray | None = None) -> None:
        inst = self.instances[b]
        inst.set_time(t)
        if self.inputs and u is not None:
            self._input_setters[b](u)
        if self.n:
            inst.set_continuous_states(x)

    def read(self, b: int, out: np.ndarray) -> None:
        """Derivatives and variables of instance b at its current point into out[:n+k]."""
        n = self.n
        if n:
            self.instances[b].derivatives_into(out[:n])
        if self.k:
            self._readers[b](out[n:])

    def evaluate(self, rows: Sequence[int], t: np.ndarray, x: np.ndarray, u: np.ndarray | None = None,
                 jac_x: bool = False, jac_p: bool = False):
        """Evaluate the instances `rows` at t[r], x[r] (and inputs u[r]).

        Returns (out [R, n+k], Jx [R, n+k, n] or None, Jp [R, n+k, P] or None).
        """
        R, n, w = len(rows), self.n, self.width
        out = np.empty((R, w))
        Jx = np.empty((R, w, n)) if jac_x else None
        Jp = np.empty((R, w, self.P)) if jac_p and self.P else None
        for r, b in enumerate(rows):
            ur = None if u is None else u[r]
            self.set_point(b, float(t[r]), x[r], ur)
            self.read(b, out[r])
            if not (_finite(x[r]) and _finite(out[r])):
                # A diverged simulation (a line-search trial far out): no derivative exists there,
                # and finite differences of inf - inf only flood the log with numpy warnings.
                for J in (Jx, Jp):
                    if J is not None:
                        J[r] = np.nan
                continue
            if jac_x:
                self._jacobian_x(b, x[r], out[r], Jx[r])
            if Jp is not None:
                self._jacobian_p(b, x[r], out[r], Jp[r])
        self.n_evaluations += R
        return out, Jx, Jp

    def _jacobian_x(self, b: int, x: np.ndarray, base: np.ndarray, J: np.ndarray) -> None:
        """J = d out / dx at instance b's current point, the columns JacobianSparsity skips zero."""
        J[:] = 0.0
        sparsity = self.sparsity
        unchecked = sparsity.unchecked
        steps = None if self._directional_x else fd_steps(x, self.nominal)   # one perturbation size per state
        if unchecked.size and self._probe(b, x, base, unchecked, sparsity.unchecked_weights, steps):
            sparsity.found(unchecked[self._state_columns(b, x, base, unchecked, steps).any(axis=0)])
        columns = sparsity.columns
        if columns.size:
            self._state_columns(b, x, base, columns, steps, J)
        self.n_jacobian_columns += len(columns)

    def _state_columns(self, b: int, x: np.ndarray, base: np.ndarray, columns: np.ndarray,
                       steps: np.ndarray | None = None, J: np.ndarray | None = None) -> np.ndarray:
        """The Jacobian columns d out / dx_i, i in columns: [n+k, len(columns)]; `steps`: fd_steps at x.
        With `J` ([n+k, n]) they are written into its columns instead (and J returned)."""
        if self._directional_x:
            try:
                result = self._directional(b, [self.state_vrs[i] for i in columns], np.eye(len(columns)))
                if J is None:
                    return result
                J[:, columns] = result
                return J
            except FmuCallError:
                self._directional_x = False  # the FMU rejects some pair: use finite differences from now on
        inst = self.instances[b]
        if steps is None:
            steps = fd_steps(x, self.nominal)
        # Python floats in the loop (the same IEEE sums as numpy's scalars, without their overhead).
        x_values, step_values = x.tolist(), steps.tolist()
        xp = x.copy()
        row = np.empty(self.width)
        result = np.empty((self.width, len(columns))) if J is None else J
        for j, i in enumerate(columns.tolist()):
            xp[i] = perturbed = x_values[i] + step_values[i]
            inst.set_continuous_states(xp)
            self.read(b, row)
            np.subtract(row, base, out=row)
            np.divide(row, perturbed - x_values[i], out=result[:, j if J is None else i])
            xp[i] = x_values[i]
        inst.set_continuous_states(x)
        return result

    def _probe(self, b: int, x: np.ndarray, base: np.ndarray, columns: np.ndarray, weights: np.ndarray,
               steps: np.ndarray | None = None) -> bool:
        """Whether perturbing the states `columns` together (distinct weights, so that exact
        cancellation of their effects is not to be expected) changes any unknown."""
        if self._directional_x:
            try:
                return bool(self._directional(b, [self.state_vrs[i] for i in columns], weights[None, :]).any())
            except FmuCallError:
                self._directional_x = False
        inst = self.instances[b]
        if steps is None:
            steps = fd_steps(x, self.nominal)
        xp = x.copy()
        xp[columns] += weights * steps[columns]
        inst.set_continuous_states(xp)
        row = np.empty(self.width)
        self.read(b, row)
        inst.set_continuous_states(x)
        return not np.array_equal(row, base)

    def _directional(self, b: int, knowns: Sequence[int], seeds: np.ndarray) -> np.ndarray:
        """One directional derivative of the unknowns per seed row: [n+k, len(seeds)]."""
        inst = self.instances[b]
        return np.stack([inst.get_directional_derivative(self.unknown_vrs, knowns, seed) for seed in seeds], axis=1)

    def _jacobian_p(self, b: int, x: np.ndarray, base: np.ndarray, J: np.ndarray) -> None:
        """Columns for the tunable parameters in continuous-time mode."""
        if self._directional_p:
            try:
                J[:] = self._directional(b, self.param_vrs, np.eye(self.P))
                return
            except FmuCallError:
                self._directional_p = False
        inst = self.instances[b]
        values = inst.get_real(self.param_vrs)
        row = np.empty(self.width)
        for j, vr in enumerate(self.param_vrs):
            value = values[j] + FD_RELATIVE_STEP * max(abs(values[j]), 1.0)
            self._with_parameter(b, vr, value, x, row)
            J[:, j] = (row - base) / (value - values[j])

    def _with_parameter(self, b: int, vr: int, value: float, x: np.ndarray, row: np.ndarray) -> None:
        """Read the outputs at x with one tunable parameter changed, then undo the change.

        Tunable parameters may be set in event mode only (FMI 2.0 ME); FMUs that also accept them
        in continuous-time mode are used directly. The mode is probed on first use."""
        inst = self.instances[b]
        old = inst.get_real([vr])[0]
        if self._param_mode is None:
            try:
                inst.set_real([vr], [old])
                self._param_mode = "direct"
            except FmuCallError:
                if not self.can_snapshot:
                    raise FmuBuilderError(
                        f"{self.info.model_name} accepts its tunable parameters only in event mode and cannot "
                        "save its state; its parameters cannot be trained") from None
                self._param_mode = "event"
        if self._param_mode == "direct":
            inst.set_real([vr], [value])
            inst.set_continuous_states(x)
            self.read(b, row)
            inst.set_real([vr], [old])
            inst.set_continuous_states(x)
            return
        self._pre[b] = inst.get_fmu_state(self._pre[b])
        # No event iteration: the column is the change at fixed discrete states.
        inst.enter_event_mode()
        inst.set_real([vr], [value])
        inst.enter_continuous_time_mode()
        inst.set_continuous_states(x)
        self.read(b, row)
        inst.set_fmu_state(self._pre[b])

    # -- event indicators --------------------------------------------------------------------
    def indicators(self, b: int, t: float, x: np.ndarray, u: np.ndarray | None = None) -> np.ndarray:
        self.set_point(b, t, x, u)
        return self.instances[b].get_event_indicators()

    def indicator_gradient(self, b: int, t: float, x: np.ndarray, j: int, u: np.ndarray | None = None):
        """(dz_j/dx [n], dz_j/dt) at (t, x) by finite differences; leaves the instance at (t, x)."""
        inst = self.instances[b]
        z0 = self.indicators(b, t, x, u)[j]
        steps = fd_steps(x, self.nominal)
        grad = np.empty(self.n)
        xp = x.copy()
        for i in range(self.n):
            xp[i] = x[i] + steps[i]
            delta = xp[i] - x[i]
            inst.set_continuous_states(xp)
            grad[i] = (inst.get_event_indicators()[j] - z0) / delta
            xp[i] = x[i]
        inst.set_continuous_states(x)
        dt = FD_RELATIVE_STEP * max(abs(t), 1.0)
        inst.set_time(t + dt)
        dz_dt = (inst.get_event_indicators()[j] - z0) / ((t + dt) - t)
        inst.set_time(t)
        return grad, dz_dt

    def indicator_discrete_gradient(self, b: int, t: float, x: np.ndarray, j: int, u: np.ndarray | None = None):
        """dz_j/dd [q] at (t, x) on the span of element b's shadows (each shadow's indicator against
        the nominal one: the shadows differ in their discrete states only), or None without
        shadows; leaves the instance as it was."""
        shadows = self._shadows[b]
        if not shadows:
            return None
        inst = self.instances[b]
        z0 = self.indicators(b, t, x, u)[j]
        self._here[b] = inst.get_fmu_state(self._here[b])
        dz = np.empty(len(shadows))
        for m, (handle, _) in enumerate(shadows):
            inst.set_fmu_state(handle)
            dz[m] = self.indicators(b, t, x, u)[j] - z0
        inst.set_fmu_state(self._here[b])
        return dz @ _pinv(np.array([deviation for _, deviation in shadows]).T)

    # -- events ------------------------------------------------------------------------------
    def handle_event(self, b: int, t: float, x_minus: np.ndarray, u: np.ndarray | None = None,
                     sensitivity: EventSensitivity | None = None, signs: np.ndarray | None = None,
                     state_event: bool = False) -> EventOutcome:
        """Run the event iteration of instance b at (t, x_minus); with `sensitivity`, also its
        linearisation (EventOutcome). `signs` (+1/-1 per known) orients the perturbations, so that
        at a state event (or step event: `state_event`) the perturbed pre-event state stays beyond
        the crossing."""
        inst = self.instances[b]
        self.set_point(b, t, x_minus, u)
        # No linearisation of an event at a diverged (non-finite) state: see evaluate.
        want = sensitivity is not None and self.can_snapshot and _finite(x_minus)
        if want:
            self._pre[b] = inst.get_fmu_state(self._pre[b])
        info = event_mode(inst, resume_on_terminate=True)
        changed = info.values_of_continuous_states_changed
        x_plus = inst.get_continuous_states() if changed else np.array(x_minus, dtype=float)
        outcome = EventOutcome(x_plus, changed, info.next_event_time_or_inf, info.terminate_simulation)
        if want and not info.terminate_simulation:
            started = time.perf_counter()
            self._post[b] = inst.get_fmu_state(self._post[b])
            self._event_sensitivity(b, t, x_minus, u, outcome, sensitivity, signs, state_event)
            inst.set_fmu_state(self._post[b])
            sensitivity.seconds += time.perf_counter() - started
        return outcome

    def _event_sensitivity(self, b, t, x_minus, u, outcome: EventOutcome, sensitivity: EventSensitivity, signs,
                           state_event: bool = False):
        inst, n = self.instances[b], self.n
        base = np.empty(self.width)
        self.read(b, base)
        d0 = self._d_getters[b]()
        modes = np.sign(inst.get_event_indicators()) if self.nz and self.q else None   # see _propagate_shadows
        knowns = n + self.P
        changed, x_plus = outcome.values_changed, outcome.x_plus
        R = np.eye(n, knowns) if changed else None
        B = np.zeros((self.carrier_width, knowns))
        pool, candidates = self._next_pool(b), _Candidates()
        shadows = sensitivity.keep_shadows()
        steps = fd_steps(x_minus, self.nominal)
        params = inst.get_real(self.param_vrs) if self.P else np.zeros(0)
        signs = np.ones(knowns) if signs is None else signs
        amounts = signs * np.concatenate([steps, FD_RELATIVE_STEP * np.maximum(np.abs(params), 1.0)])
        columns, unchecked = sensitivity.columns(), sensitivity.unchecked()
        if unchecked.size:
            probe = np.zeros(knowns)
            probe[unchecked] = sensitivity.probe_weights[unchecked] * amounts[unchecked]
            x_probe = self._redo_event(b, x_minus, params, probe)
            dd, df, dx = self._measure(b, x_plus, base, d0, changed)
            if df.any() or (self.q and dd.any()) or (changed and not np.array_equal(dx, x_probe - x_minus)):
                columns = np.arange(knowns)   # some unchecked known acts: perturb each this time
        nonzero = np.zeros(len(columns), dtype=bool)
        for c, i in enumerate(columns):
            perturbation = np.zeros(knowns)
            perturbation[i] = amounts[i]
            x_perturbed = self._redo_event(b, x_minus, params, perturbation)
            delta = x_perturbed[i] - x_minus[i] if i < n else (params[i - n] + amounts[i]) - params[i - n]
            dd, df, dx = self._measure(b, x_plus, base, d0, changed)
            self._column(b, i, delta, (dd, df, dx), R, B, d0, candidates, pool if shadows else None)
            nonzero[c] = _any(df) or (self.q and _any(dd)) or not (R is None or _identity_column(R, i, n))
        sensitivity.observe(columns, nonzero, probes=int(unchecked.size > 0))
        outcome.R, outcome.B = R, B
        if self.q:
            self._propagate_shadows(b, t, x_minus, u, outcome, base, d0, candidates, pool, sensitivity, shadows,
                                    state_event, modes, amounts[:n])

    def _column(self, b, i, delta, measured, R, B, d0, candidates: _Candidates, pool) -> None:
        """Column i of R and B from the deviations `measured` after perturbing known i by delta;
        a discrete deviation is a candidate shadow (with a snapshot from `pool`, if one is given)."""
        dd, df, dx = measured
        if R is not None:
            R[:, i] = dx / delta
        B[:, i] = (dd if self.q else df) / delta
        if self.q and _nonzero(dd, d0):
            candidates.add(dd, df, dx, None if pool is None else self._snapshot(b, pool, len(candidates.handles)))

    def _redo_event(self, b, x_minus, params, perturbation) -> np.ndarray:
        """The event iteration of instance b again, from the snapshot before the event, with the
        knowns (x-, p) perturbed; the parameters are set back after it (shadows must carry nominal
        parameters: the perturbation acted through the event). Returns the perturbed x-."""
        inst, n = self.instances[b], self.n
        inst.set_fmu_state(self._pre[b])
        x_perturbed = x_minus + perturbation[:n]
        if _any(perturbation[:n]):
            inst.set_continuous_states(x_perturbed)
        if _any(perturbation[n:]):
            event_mode(inst, before_iteration=lambda: inst.set_real(self.param_vrs, params + perturbation[n:]),
                       after_iteration=lambda: inst.set_real(self.param_vrs, params), resume_on_terminate=True)
        else:
            event_mode(inst, resume_on_terminate=True)
        return x_perturbed

    def _measure(self, b, x_plus, base, d0, changed):
        """After a perturbed event iteration: (discrete, output, reset) deviations from nominal, read
        with the continuous states put back to the nominal x+ (so only the discrete path shows)."""
        inst = self.instances[b]
        dx = inst.get_continuous_states() - x_plus if changed else None
        inst.set_continuous_states(x_plus)
        row = np.empty(self.width)
        self.read(b, row)
        dd = self._d_getters[b]() - d0 if self.q else None
        return dd, row - base, dx

    def _propagate_shadows(self, b, t, x_minus, u, outcome, base, d0, candidates, pool, sensitivity, keep,
                           state_event: bool = False, modes: np.ndarray | None = None, push=None):
        """Redo the event on each shadow (nominal continuous state, perturbed discrete state from the
        previous event): gives A (and Rd) on the shadows' span; then G by regression over all
        candidates, and at most q independent candidates become the new shadows. A shadow whose
        indicators' signs differ from the nominal `modes` took another branch (solve.py, item 3):
        it is measured on the nominal branch (_beyond), left out only where that fails."""
        inst = self.instances[b]
        d_in, d_out, x_out = [], [], []
        for handle, deviation in self._shadows[b]:
            inst.set_fmu_state(handle)
            self.set_point(b, t, x_minus, u)
            event_mode(inst, resume_on_terminate=True)
            dd, df, dx = self._measure(b, outcome.x_plus, base, d0, outcome.values_changed)
            sensitivity.propagations += 1
            if modes is not None and not np.array_equal(np.sign(inst.get_event_indicators()), modes):
                measured = None if push is None else self._beyond(b, handle, t, x_minus, u, outcome, base, d0,
                                                                  modes, push, sensitivity)
                if measured is None:
                    continue
                dd, df, dx = measured
            d_in.append(deviation)
            d_out.append(dd)
            x_out.append(dx)
            if _nonzero(dd, d0):
                sensitivity.memory_seen = True
                handle = self._snapshot(b, pool, len(candidates.handles)) if keep else None
                candidates.add(dd, df, dx, handle)
        if d_in:
            sensitivity.state_event_checked |= state_event
            inverse = _pinv(np.array(d_in).T)
            outcome.A = np.array(d_out).T @ inverse
            if outcome.values_changed:
                outcome.Rd = np.array(x_out).T @ inverse
        outcome.G = _regression(candidates, self.width, self.q)
        self._shadows[b] = _independent(candidates, self.q) if keep else []

    def _beyond(self, b, handle, t, x_minus, u, outcome, base, d0, modes, push, sensitivity):
        """A shadow's deviations on the nominal branch of the event: the shadow and the nominal
        event redone at x- + s push (push: the perturbations oriented beyond the crossing), s
        doubled until the shadow crosses too; their difference is the shadow's effect at first
        order (the push acts on both alike). Leaves the instance in the shadow's post-event state
        (continuous states nominal), the next shadow's snapshot. None when no s up to
        2^MAX_PUSH_DOUBLINGS brings it across or the push moves the nominal off its branch."""
        inst = self.instances[b]
        scale = 1.0
        for _ in range(MAX_PUSH_DOUBLINGS):
            scale *= 2.0
            x_pushed = self._redo_event(b, x_minus, None, scale * push)
            sensitivity.propagations += 1
            if not np.array_equal(np.sign(inst.get_event_indicators()), modes):
                return None
            nominal = self._measure(b, outcome.x_plus, base, d0, outcome.values_changed)
            inst.set_fmu_state(handle)
            self.set_point(b, t, x_pushed, u)
            event_mode(inst, resume_on_terminate=True)
            sensitivity.propagations += 1
            if np.array_equal(np.sign(inst.get_event_indicators()), modes):
                shadow = self._measure(b, outcome.x_plus, base, d0, outcome.values_changed)
                return tuple(None if s is None else s - n for s, n in zip(shadow, nominal))
        return None

    def init_sensitivity(self, b: int, x_init: np.ndarray, restarts) -> EventOutcome:
        """Linearisation of the initialization with respect to (x0, p): `restarts[i]()` re-initializes
        instance b with known i perturbed and returns the perturbation. The caller re-initializes
        the nominal case afterwards."""
        n, knowns = self.n, len(restarts)
        base = np.empty(self.width)
        self.read(b, base)
        d0 = self._d_getters[b]()
        R = np.zeros((n, knowns))
        B = np.zeros((self.carrier_width, knowns))
        pool, candidates = self._next_pool(b), _Candidates()
        for i, restart in enumerate(restarts):
            delta = restart()
            self._column(b, i, delta, self._measure(b, x_init, base, d0, True), R, B, d0, candidates, pool)
        outcome = EventOutcome(x_init, True, np.inf, False, R=R, B=B)
        if self.q:
            outcome.G = _regression(candidates, self.width, self.q)
            self._shadows[b] = _independent(candidates, self.q)
        return outcome

    def _next_pool(self, b: int) -> list:
        """The snapshot pool not holding the current shadows."""
        self._turn[b] ^= 1
        return self._pools[b][self._turn[b]]

    def _snapshot(self, b: int, pool: list, slot: int):
        inst = self.instances[b]
        if slot < len(pool):
            return inst.get_fmu_state(pool[slot])
        pool.append(inst.get_fmu_state())
        return pool[-1]


def _finite(values: np.ndarray) -> bool:
    """Whether every value is finite; for the few values of one FMU evaluation a Python loop is
    cheaper than numpy's isfinite().all()."""
    return all(map(math.isfinite, values.tolist()))


def _any(values: np.ndarray) -> bool:
    """values.any() without its Python-level wrapper (called several times per event)."""
    return np.count_nonzero(values) > 0


def _identity_column(R: np.ndarray, i: int, n: int) -> bool:
    return bool((R[:, i] == (np.arange(n) == i)).all()) if i < n else not R[:, i].any()


def _nonzero(dd: np.ndarray, d0: np.ndarray) -> bool:
    """A discrete deviation worth tracking: above round-off of the discrete values."""
    size = float(np.abs(dd).max(initial=0.0))
    return size > 0.0 and size > 1e-13 * float(np.abs(d0).max(initial=0.0))


def _regression(candidates: _Candidates, width: int, q: int) -> np.ndarray:
    """G with df = G dd over the candidates (least squares on their span)."""
    if not candidates.dd:
        return np.zeros((width, q))
    return np.array(candidates.df).T @ _pinv(np.array(candidates.dd).T)


def _pinv(a: np.ndarray) -> np.ndarray:
    """Pseudo-inverse; the one-row and one-column cases (the common ones) without an SVD."""
    if a.shape[0] == 1 or a.shape[1] == 1:
        norm2 = float((a * a).sum())
        return a.T / norm2 if norm2 > 0 else np.zeros(a.T.shape)
    return np.linalg.pinv(a, rcond=1e-10)


def _independent(candidates: _Candidates, q: int) -> list:
    """Up to q candidates with linearly independent discrete deviations (Gram-Schmidt, in order)."""
    basis, chosen = [], []
    for j, dd in enumerate(candidates.dd):
        v = dd / np.linalg.norm(dd)
        for e in basis:
            v = v - (e @ v) * e
        r = np.linalg.norm(v)
        if r > 1e-6:
            basis.append(v / r)
            chosen.append((candidates.handles[j], dd))
            if len(chosen) == q:
                break
    return chosen


def fmu_call(evaluator: FmuEvaluator, rows: Sequence[int], t: np.ndarray, x: torch.Tensor, p: torch.Tensor,
             u: np.ndarray | None = None) -> torch.Tensor:
    """Differentiable evaluation: out [R, n+k] = [derivatives | variables] of the instances `rows`.

    x: tensor [R, n]; p: tensor [P] of the trained tunable parameters (may be empty)."""
    return FmuFunction.apply(x, p, evaluator, rows, t, u)


class FmuFunction(torch.autograd.Function):
    """Jacobians are computed in forward, and only for the inputs that need a gradient."""

    @staticmethod
    def forward(ctx, x, p, evaluator, rows, t, u):
        want_x, want_p = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        out, Jx, Jp = evaluator.evaluate(rows, t, x.detach().numpy(), u, jac_x=want_x, jac_p=want_p)
        ctx.Jx = None if Jx is None else torch.from_numpy(Jx)
        ctx.Jp = None if Jp is None else torch.from_numpy(Jp)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad_out):
        gx = gp = None
        g = grad_out.unsqueeze(1)
        if ctx.Jx is not None:
            gx = torch.bmm(g, ctx.Jx).squeeze(1)
        if ctx.Jp is not None:
            gp = torch.bmm(g, ctx.Jp).squeeze(1).sum(0)
        return gx, gp, None, None, None, None
