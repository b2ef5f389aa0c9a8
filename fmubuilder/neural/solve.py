"""Differentiable simulation of a NeuralFMU with the FMI 2.0 event semantics.

Batch elements run side by side (B FMU instances, states a [B, n] tensor), fixed-step Euler or RK4
on the grid t0_b + k h, each element through its own event sequence towards its next grid point
(docs/ARCHITECTURE.md, "Event handling"); a state event is located without gradients on the step's
dense output (Euler: linear; RK4: cubic Hermite). The first step from a grid point starts every
element there: its first stage is the record. Under torch.no_grad() nothing below is done.

Gradients across events:
1. Event time. With t* the located time and z the crossing indicator,
       t_e = t* - (z(t*, x(t*)) - value) / (dz/dt)
   is evaluated with grad: its value is t* exactly and its gradient is the implicit-function
   (saltation) sensitivity -z_x dx/dtheta / zdot. The pre-event state is the dense output at t_e,
   the step after the event has length t_next - t_e, so autograd carries dt_e/dtheta into both.
   The indicator gradient z_x (and dz/dt) come from finite differences, at state events only. An
   indicator may also depend on discrete states held since the last event (the VLDM's start margin
   on the held driver error): with shadows (3b) its gradient z_d on their span is read from their
   indicators at (t*, x(t*)), and z_d dd (dd the element's carrier) joins z_x dx in the shift.
2. Reset map. If the FMU reports valuesOfContinuousStatesChanged, x+ = x+_value + R (x- - x-.detach())
   with R = dx+/dx- by finite differences through the event iteration; otherwise x+ is x- itself.
3. Discrete states. Sampled controllers and relays keep discrete states d inside the FMU that are
   set at events and drive the derivatives until the next event; without their path the gradient of
   a closed loop can have the wrong sign. At each event the FMU state before the event is saved
   (fmi2GetFMUstate); for each state i it is restored, x-_i perturbed, the event iteration redone,
   the continuous states set back to the nominal x+, and the derivatives and recorded variables
   read: their change is the effect through the discrete states only.
   a) Memoryless fallback (the FMU exposes no discrete Real variable): M = d(der, vars)/dx- from
      these perturbations; until the element's next event every FMU evaluation adds
      M (x- - x-.detach()): zero in value, the discrete-state path in the gradient. Exact when the
      discrete states are functions of the latest pre-event state (a held sample).
   b) Discrete states with memory (a discrete integrator, d+ = D(x-, d-)): when the FMU exposes its
      discrete Real variables (variability="discrete"), they are read after each perturbation, which
      gives B = dd+/dx-. A zero-valued carrier dd [q] per element follows dd+ = B dev + A dd- and
      every FMU evaluation adds G dd+ (G = d(der, vars)/dd by least squares over the perturbations).
      A = dd+/dd- needs perturbed discrete states, which FMI cannot set: they are kept as *shadow*
      snapshots (at most q, linearly independent, taken from the perturbed post-event states); at
      the next event each shadow is restored, given the nominal time and continuous state, and its
      event iteration redone. This reduces to a) for memoryless discrete states, costs n + q event
      iterations per event, and is exact to first order as long as the exposed discrete variables
      are the FMU's discrete state.
   Trained tunable FMU parameters are perturbed like states (set in event mode); at state events
   the perturbations are oriented so that the perturbed state stays beyond the crossing. Knowns
   without effect at the previous event are probed together (layer.EventSensitivity; the count and
   time in Trajectory.stats["event_sensitivity"]). A held sample (the VLDM's driver error) is
   memoryless at the ticks that resample it but has memory across a state event between two ticks
   (A = 1 there): shadows are kept until they have been through a state event, and for good once
   they show memory. A shadow that takes another branch at a state event (its indicators' signs
   differ from the nominal ones: it has not crossed yet, item 1) is measured on the nominal branch:
   the shadow and the nominal event redone with x- pushed further across, their difference taken
   (layer.FmuEvaluator._beyond); left out only where no push up to 2^10 steps works.
   Limits: an event of an element restarts its memoryless M (case a), which drops a held sample's
   path at a state event between ticks; an FMU that cannot save its state gets no discrete-state
   path (a warning says so); G (and M) are measured at the event's x+ and held until the next
   event, so where d(der)/dd varies with x in between the inner solver stages get it slightly
   wrong (docs/MEASUREMENTS.md, "Gradients and speed", measured by benchmarks/bench_gradient.py).
4. Initial state. For a fresh initialization with x0 or FMU parameters requiring grad, the same is
   done for the initialization: one re-initialization per perturbed start value (needs fmi2Reset);
   its perturbed states seed the shadows.

The FMU itself has no time gradient: its explicit time dependence inside a split step is ignored
(inputs from data need none).
"""
from __future__ import annotations

import math
import time as _time
import warnings
from collections import namedtuple
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import torch

from ..errors import FmuBuilderError
from ..simulation.events import EVENT, EventSequence, crossed, event_mode, locate, time_scale
from ..simulation.inputs import InputSignals
from ..simulation.solvers import hermite, rk4_step
from .layer import EventSensitivity, FmuEvaluator, fd_steps, fmu_call
from .model import NeuralFMU
from .system import NumpyTopology

SOLVERS = ("euler", "rk4")
# The batched step whose ends the elements' sequences are sent: the elements' rows in it, the states
# before (every element's), its first stages, the states after (tensor and numpy), the corrections,
# the discrete-state carriers (every element's, or None).
# natural: with forcing, the step's ends before the forced states were set (else None)
_Stepping = namedtuple("_Stepping", "position x dx1 x_new x_np c dd natural")


@dataclass
class ElementStart:
    """Where one batch element starts: a fresh initialization at t0, a saved FMU state, or (for an
    FMU that cannot save its state) a replay of the run that reached it (see Replay)."""
    t0: float
    fmu_state: bytes | None = None            # serialized FMU state (continuous-time mode) at t0
    next_event_time: float = math.inf         # the FMU's time event pending at the saved state
    states: dict[str, float] | None = None    # continuous states to override (e.g. measured values)
    replay: "Replay | None" = None            # how to reach this start again without a saved state
    instance: object = field(default=None, repr=False, compare=False)  # an FMU instance standing at
                                              # this start (continuous-time mode); one run takes it


@dataclass
class Replay:
    """How an FMU without fmi2GetFMUstate reaches a start again: the hybrid with the topology's
    parameters `parameters` simulated without gradient for `duration` seconds from `origin`.

    The run that ends at a start leaves its FMU instance standing there (ElementStart.instance):
    the next run that starts there continues that instance, at no cost (carry-over from element
    to element, sequential elements). Only a start used a second time (a rewind, the same starts
    measured twice) or saved in the middle of a run (captured element starts) is replayed, which
    costs one simulation without gradient from the origin, recursively back to a start that still
    holds its instance or is a fresh initialization. The replay repeats the original run's steps,
    events and FMU calls, so it reaches the same FMU state (continuous and discrete), up to
    rounding (a run with gradient evaluates the ANN in torch, a replay in numpy)."""
    origin: ElementStart
    duration: float
    parameters: dict
    step_size: float
    solver: str
    inputs: InputSignals | None


@dataclass
class Trajectory:
    """Recorded values on the grid: `values[k, b, j]` is variable names[j] of element b at t0[b] + times[k]."""
    times: np.ndarray
    t0: np.ndarray
    names: list[str]
    values: torch.Tensor
    final_states: torch.Tensor
    final_starts: list[ElementStart] | None = None
    captured: dict[int, list[ElementStart]] = field(default_factory=dict)
    stats: dict = field(default_factory=dict)
    # With RK4, what a sensor needs besides the grid: `before[k, b, j]`, the value at grid point k + 1
    # before the events there (`values` holds the one after them, the start of the next step), and
    # `inner`, the steps of the grid intervals an event cuts: (k, b, [(start, end, value at the
    # start, value at the end before its events), ...]), times from t0[b] (see neural/sensor.py).
    before: torch.Tensor | None = None
    inner: list = field(default_factory=list)

    def signal(self, name: str) -> torch.Tensor:
        """[T, B] values of one recorded variable."""
        if name not in self.names:
            raise FmuBuilderError(f"'{name}' was not recorded; record it with record=[..., '{name}']")
        return self.values[:, :, self.names.index(name)]

    def numpy(self, name: str) -> np.ndarray:
        return self.signal(name).detach().numpy()


def simulate(model: NeuralFMU, duration: float, step_size: float, *, starts: Sequence[ElementStart] | None = None,
             t_start: float = 0.0, x0: torch.Tensor | None = None, record: Sequence[str] = (),
             solver: str = "euler", inputs: InputSignals | None = None, keep_final_state: bool = False,
             capture: Sequence[int] = (), event_gradients: bool = True,
             sensitivity: EventSensitivity | None = None, forcing=None) -> Trajectory:
    """Simulate `model` for `duration` seconds with a fixed step from each start.

    starts: one ElementStart per batch element (default: one fresh start at t_start).
    x0: optional tensor [B, n] of initial continuous states (may require grad).
    record: variables to record on the grid (states, derivatives = hybrid derivatives, FMU variables).
    capture: grid indices k at which every element's FMU state is saved into Trajectory.captured.
    keep_final_state: save each element's final FMU state into Trajectory.final_starts.
    forcing: (state indices, f(t [B]) -> values [B, len(indices)]): those states are set to the given
    values after every step (no gradient; used by collocation). A state event the step's own course
    crosses is located there; else the forced end is checked for one.
    """
    starts = list(starts) if starts else [ElementStart(float(t_start))]
    if not can_snapshot(model.info):
        starts = [_reachable(model, start) for start in starts]
    run = _Run(model, starts, duration, step_size,
               solver, list(record), inputs, x0, keep_final_state, set(capture), event_gradients, sensitivity,
               forcing)
    try:
        return run.run()
    finally:
        run.ev.free()


def can_snapshot(info) -> bool:
    """Whether element starts are saved FMU states (else they are replays, see Replay)."""
    caps = info.capabilities
    return caps.can_get_and_set_fmu_state and caps.can_serialize_fmu_state


def _reachable(model: NeuralFMU, start: ElementStart) -> ElementStart:
    """`start` made ready for a run of an FMU without saved states: a fresh start, or one whose
    FMU instance stands at it (replayed here when no instance holds it any more)."""
    start = _without_empty_replay(start)
    chain = [start]   # back to a start that is fresh or still held
    while chain[-1].replay is not None and not model.holds(chain[-1]):
        chain.append(_without_empty_replay(chain[-1].replay.origin))
    for position in range(len(chain) - 2, -1, -1):
        _replay(model, chain[position], chain[position + 1])
    return start


def _without_empty_replay(start: ElementStart) -> ElementStart:
    """A start captured at the very beginning of a run is that run's start (with both overrides)."""
    while start.replay is not None and start.replay.duration <= 0 and start.instance is None:
        origin = start.replay.origin
        start = ElementStart(origin.t0, origin.fmu_state, origin.next_event_time,
                             {**(origin.states or {}), **(start.states or {})}, origin.replay)
    return start


def _replay(model: NeuralFMU, start: ElementStart, origin: ElementStart) -> None:
    """Run start.replay from `origin` (ready: fresh or held) and leave the instance standing at `start`."""
    recipe = start.replay
    current = {name: value.detach().clone() for name, value in model.topology.state_dict().items()}
    try:
        with torch.no_grad():
            model.topology.load_state_dict(recipe.parameters)
            run = _Run(model, [origin], recipe.duration, recipe.step_size, recipe.solver, [], recipe.inputs,
                       None, True, set(), False, EventSensitivity(model.event_sensitivity.n_knowns))
            try:
                final = run.run().final_starts[0]
            finally:
                run.ev.free()
    finally:
        with torch.no_grad():
            model.topology.load_state_dict(current)
    start.next_event_time = final.next_event_time
    model.hold(final.instance, start)
    model.replays["runs"] += 1
    model.replays["simulated_seconds"] += recipe.duration


def _x0_values(x0: torch.Tensor, B: int, n: int) -> np.ndarray:
    if x0.numel() != B * n:
        raise FmuBuilderError(f"x0 needs {B * n} values ({B} elements of {n} states), got shape {tuple(x0.shape)}")
    return x0.detach().numpy().reshape(B, n).astype(float)


def batch_matvec(matrices: np.ndarray, vectors: torch.Tensor) -> torch.Tensor:
    """[B, i, j] (numpy) times [B, j] -> [B, i]."""
    return torch.bmm(torch.from_numpy(matrices), vectors.unsqueeze(-1)).squeeze(-1)


class _Run:
    def __init__(self, model: NeuralFMU, starts, duration, step_size, solver, record, inputs, x0,
                 keep_final_state, capture, event_gradients, sensitivity, forcing=None):
        if solver not in SOLVERS:
            raise FmuBuilderError(f"unknown solver '{solver}': choose one of {', '.join(SOLVERS)}")
        if not (step_size > 0 and math.isfinite(step_size)):
            raise FmuBuilderError(f"step size must be a positive number, got {step_size}")
        if not (duration > 0 and math.isfinite(duration)):
            raise FmuBuilderError(f"duration must be a positive number, got {duration}")
        self.model, self.topology, self.info = model, model.topology, model.info
        self.starts = starts
        self.B = len(starts)
        self.n = self.info.n_states
        self.h = float(step_size)
        self.K = max(1, int(math.ceil(duration / self.h - 1e-9)))
        self.grid = np.minimum(np.arange(self.K + 1) * self.h, duration)
        self.grid[-1] = duration
        self.rk4 = solver == "rk4"
        self.inputs = inputs
        self.keep_final_state = keep_final_state
        self.capture = capture
        self.snapshots = can_snapshot(self.info)
        self.instances = model.instances_for(starts)
        self.rows = list(range(self.B))
        state_names = model.state_names()
        derivative_names = [v.name for v in self.info.derivatives]
        variables = list(self.topology.fmu_variables)
        self.record_source = []
        for name in record:
            self.info.variable(name)
            if name in state_names:
                self.record_source.append(state_names.index(name))
            elif name in derivative_names:
                self.record_source.append(self.n + derivative_names.index(name))
            else:
                if name not in variables:
                    variables.append(name)
                self.record_source.append(2 * self.n + variables.index(name))
        self.record_names = list(record)
        self.record_index = torch.tensor(self.record_source, dtype=torch.long)
        self.ev = FmuEvaluator(self.instances, self.info, variables, inputs.names if inputs else (),
                               model.config.parameters)
        self.p = self.topology.fmu_parameters
        self.ann = None      # the folded ANN (Topology.folded) of a run with gradients
        self.kernel = None   # its numpy evaluation (system.NumpyTopology) in a run without
        self.x0 = x0
        self.grad = torch.is_grad_enabled() and (
            (x0 is not None and x0.requires_grad) or any(q.requires_grad for q in model.parameters()))
        self.event_grad = self.grad and event_gradients
        if self.event_grad and not self.ev.can_snapshot:
            warnings.warn(f"{self.info.model_name} cannot get/set its FMU state: gradients treat its discrete "
                          "states as constants at events and its state resets as constant", stacklevel=3)
        self.sens = sensitivity or model.event_sensitivity
        self.sens.start_run()
        self.first_events = np.full(self.B, math.inf)   # each element's next time event at its start
        self.elements: list[EventSequence] = []          # where each element stands in the event sequence
        self.counts = {"steps": 0, "time_events": 0, "state_events": 0, "step_events": 0}
        self.step_events = not self.info.capabilities.completed_integrator_step_not_needed
        self.t_grad = {}   # element -> its time, a located event time that carries a gradient
        self.segments = None   # with RK4, the steps of the current grid interval (_keep_segment)
        if forcing is not None and self.grad:
            raise FmuBuilderError("forced states are for simulations without gradients; use torch.no_grad()")
        self.forcing = forcing
        self.natural_cut = set()      # elements whose last step was cut on its natural course

    # -- set-up ------------------------------------------------------------------------------
    def _inputs_at(self, t) -> np.ndarray | None:
        return None if self.inputs is None else self.inputs.table(t)

    def _u(self, b: int, t: float):
        return None if self.inputs is None else self.inputs.table(t)[0]

    def initialise(self):
        """Start every element; returns (x [B, n], dd carrier or None, correction c or None)."""
        n, B = self.n, self.B
        self.t0 = np.array([s.t0 for s in self.starts], dtype=float)
        x0_values = None if self.x0 is None else _x0_values(self.x0, B, n)
        x = np.empty((B, n))
        init_outcomes = {}
        init_sens = self.grad and self.ev.can_snapshot and (
            (self.x0 is not None and self.x0.requires_grad) or self.p.requires_grad)
        for b, start in enumerate(self.starts):
            self.ev.forget_shadows(b)
            overrides = dict(start.states or {})
            if x0_values is not None:
                overrides.update(zip(self.model.state_names(), x0_values[b]))
            if start.fmu_state is None and start.replay is not None:
                x[b] = self._continue(b, start, overrides)
            elif start.fmu_state is None:
                x[b], self.first_events[b] = self._fresh_init(b, overrides)
                if init_sens:
                    init_outcomes[b] = self._init_sensitivity(b, overrides, x[b])
            else:
                x[b] = self._restore(b, start, overrides)
        self.ev.refresh_nominals()
        x_t, dd, c = torch.from_numpy(x), None, None
        x0_t = None if self.x0 is None else self.x0.reshape(B, n)
        if x0_t is not None and x0_t.requires_grad:
            x_t = x_t + (x0_t - x0_t.detach())  # restored starts take x0 as it is
        if init_outcomes:
            # fresh starts follow the initialization x_init(x0, p) and its discrete states
            dev = self._known_deviation(x0_t if x0_t is not None else torch.from_numpy(x))
            rows = np.array(sorted(init_outcomes))
            mask = np.zeros(B, dtype=bool)
            mask[rows] = True
            x_init, dd, c = self._linearised_event(x_t, dev, {b: init_outcomes[b] for b in rows}, None, None, mask)
            x_t = x_init
        return x_t, dd, c

    def _fresh_init(self, b: int, overrides: dict) -> tuple[np.ndarray, float]:
        inst = self.instances[b]
        inst.reset()
        t0 = float(self.starts[b].t0)
        inst.setup_experiment(start_time=t0)
        inst.set(self.model.start_values_with_parameters())
        if self.inputs is not None:
            inst.set_real(self.ev.input_vrs, self._u(b, t0))
        inst.set(overrides)
        inst.enter_initialization_mode()
        inst.exit_initialization_mode()
        info = event_mode(inst, entered=True)
        if info.terminate_simulation:
            raise FmuBuilderError(f"{self.info.model_name} asked to terminate during initialization")
        return inst.get_continuous_states(), info.next_event_time_or_inf

    def _init_sensitivity(self, b: int, overrides: dict, x_init: np.ndarray):
        """Linearisation of the initialization of element b, one re-initialization per known."""
        names = self.model.state_names()
        x0 = np.array([overrides.get(name, x_init[i]) for i, name in enumerate(names)], dtype=float)
        params = self.p.detach().numpy()
        steps = fd_steps(x0, np.ones(self.n))

        def restart(i):
            def run():
                perturbed = dict(overrides)
                if i < self.n:
                    perturbed[names[i]] = x0[i] + steps[i]
                    delta = perturbed[names[i]] - x0[i]
                else:
                    name = self.model.config.parameters[i - self.n]
                    value = params[i - self.n] + 1e-7 * max(abs(params[i - self.n]), 1.0)
                    perturbed[name] = value
                    delta = value - params[i - self.n]
                self._fresh_init(b, perturbed)
                if i >= self.n:  # back to the nominal parameter: shadows must differ in discrete states only
                    self._set_parameters(b, [self.ev.param_vrs[i - self.n]], [params[i - self.n]])
                return delta
            return run
        outcome = self.ev.init_sensitivity(b, x_init, [restart(i) for i in range(self.n + self.ev.P)])
        self._fresh_init(b, overrides)
        return outcome

    def _restore(self, b: int, start: ElementStart, overrides: dict) -> np.ndarray:
        inst = self.instances[b]
        if not self.info.capabilities.can_serialize_fmu_state:
            raise FmuBuilderError(f"{self.info.model_name} cannot serialize its FMU state; start elements fresh instead")
        state = inst.deserialize_fmu_state(start.fmu_state)
        try:
            inst.set_fmu_state(state)
        finally:
            inst.free_fmu_state(state)
        return self._continue(b, start, overrides)

    def _continue(self, b: int, start: ElementStart, overrides: dict) -> np.ndarray:
        """Element b from its instance standing at `start` (restored or held): the trained FMU
        parameters and the state overrides applied."""
        inst = self.instances[b]
        if self.ev.P:
            self._set_parameters(b, self.ev.param_vrs, self.p.detach().tolist())
        self.first_events[b] = start.next_event_time
        x = inst.get_continuous_states()
        if overrides:
            names = self.model.state_names()
            for name, value in overrides.items():
                if name not in names:
                    raise FmuBuilderError(f"'{name}' is not a continuous state of {self.info.model_name}")
                x[names.index(name)] = float(value)
            inst.set_continuous_states(x)
        return x

    def _set_parameters(self, b: int, vrs, values) -> None:
        """Tunable parameters of element b, set in event mode (FMI 2.0 ME allows no other)."""
        inst = self.instances[b]
        event_mode(inst, before_iteration=lambda: inst.set_real(vrs, values), resume_on_terminate=True)

    def _known_deviation(self, x: torch.Tensor) -> torch.Tensor:
        """[R, n+P]: the zero-valued carriers of the gradient, (x - x.detach(), p - p.detach())."""
        dev = x - x.detach()
        if self.ev.P:
            dp = (self.p - self.p.detach()).expand(x.shape[0], self.ev.P)
            dev = torch.cat([dev, dp], dim=1)
        return dev

    # -- right-hand side and solver steps -----------------------------------------------------
    def rhs(self, rows, t: np.ndarray, x: torch.Tensor, c):
        """(hybrid derivatives [R, n], FMU results [R, n + k]) of the elements `rows`."""
        out = fmu_call(self.ev, rows, t, x, self.p, self._inputs_at(t))
        if c is not None:
            out = out + c
        if self.kernel is not None:   # no gradient wanted: the same fold in numpy is cheaper
            out_np = out.numpy()
            dx = self.kernel.rows(x.detach().numpy(), out_np[:, : self.n].copy(), out_np[:, self.n:])
            return torch.from_numpy(dx), out
        if self.ann is None:
            return out[:, : self.n], out
        return self.topology.mix(self.ann, x, out), out

    def step(self, rows, t: np.ndarray, x: torch.Tensor, h, c):
        """One step for `rows` from (t, x) over h (numpy [R] or tensor [R, 1]); returns (x_new, dx1,
        out1, the last stage's (dx, out) at t + h: RK4's fourth, None for Euler)."""
        if isinstance(h, torch.Tensor):
            h_np, h_t = h.detach().numpy()[:, 0], h
        else:
            h_np, h_t = h, torch.from_numpy(h[:, None])
        dx1, out1 = self.rhs(rows, t, x, c)
        if not self.rk4:
            return x + h_t * dx1, dx1, out1, None
        stages = []

        def f(t, x):
            stages.append(self.rhs(rows, t, x, c))
            return stages[-1][0]
        return rk4_step(f, t, x, dx1, h_t, h_np), dx1, out1, stages[-1]

    # -- main loop: the engine's event sequence, per element ----------------------------------
    def run(self) -> Trajectory:
        started = _time.perf_counter()
        # the ANN folded once per run (its gradient gathers here); none when it cannot act
        active = self.topology.has_ann and bool(self.topology.gate_ann.count_nonzero())
        if self.grad and self.topology.has_ann:
            self.ann = self.topology.folded(transposed=True)
        elif active:
            self.kernel = NumpyTopology(self.topology)
        x, dd, c = self.initialise()
        if self.forcing is not None:
            x = self._forced(self.t0, x)
        x_np = x.detach().numpy()
        for b in self.rows:   # the indicators: the reference of the first step's sign changes
            z = (self.ev.indicators(b, self.t0[b], x_np[b], self._u(b, self.t0[b]))
                 if self.info.n_event_indicators else None)
            t0, duration = float(self.t0[b]), float(self.grid[-1])     # the element's experiment, as the engine's
            self.elements.append(EventSequence(t0, float(self.first_events[b]), z, self.counts,
                                               time_scale(t0, t0 + duration), index=b))
        records, captured, before, inner = [], {}, [], []
        x, dd, c, _ = self._walk(self.t0, x, dd, c, record=False)   # the time events due at the start
        for k in range(self.K):
            if k in self.capture:
                captured[k] = self._save_states(x, self.grid[k])
            self.segments = [] if self.rk4 else None
            x, dd, c, record = self._walk(self.t0 + self.grid[k + 1], x, dd, c)
            records.append(record)
            if self.rk4:
                before.append(self._interval_ends(k, record, inner))
        tau = self.grid[self.K]
        if self.K in self.capture:
            captured[self.K] = self._save_states(x, tau)
        dx, out = self.rhs(self.rows, self._times(), x, c)
        records.append(self._record(x, dx, out))
        final_starts = self._save_states(x, tau, final=True) if self.keep_final_state else None
        stats = dict(self.counts, seconds=_time.perf_counter() - started,
                     fmu_evaluations=self.ev.n_evaluations, jacobian_columns=self.ev.n_jacobian_columns)
        if self.event_grad:
            stats["event_sensitivity"] = self.sens.stats()
        values = torch.stack(records) if records else torch.zeros(0, self.B, 0)
        return Trajectory(self.grid.copy(), self.t0, self.record_names, values, x, final_starts, captured, stats,
                          torch.stack(before) if before else None, inner)

    def _times(self) -> np.ndarray:
        return np.array([element.t for element in self.elements])

    def _walk(self, limits: np.ndarray, x, dd, c, record: bool = True):
        """Every element towards its limit (limits [B]) by the event sequence (EventSequence): the
        elements that ask to step take one batched step, the events of a kind are one batched event
        mode (state and step events before time events, the order of each element's sequence), and
        steps wait until no event is pending. With `record`, the first step is taken by every
        element (a finished one stands still): its first stage is the record. Returns
        (x, dd, c, record or None)."""
        walks, requests = {}, {}
        for b, element in enumerate(self.elements):
            if not element.terminated:
                walks[b] = element.towards(limits[b], self)
                self._resume(walks, requests, b, None)
        first_stage = None
        while requests or (record and first_stage is None):
            if any(kind is EVENT for kind, _ in requests.values()):
                rows = sorted(b for b, (kind, what) in requests.items() if kind is EVENT and what != "time")
                state = bool(rows)
                rows = rows or sorted(b for b, (kind, _) in requests.items() if kind is EVENT)
                x, dd, c = self._events(rows, x, dd, c, self.signs if state else None, state)
                for b in rows:
                    self._resume(walks, requests, b, None)
                continue
            x, recorded = self._step(walks, requests, x, c, dd, every=record and first_stage is None)
            if first_stage is None:
                first_stage = recorded
        return x, dd, c, first_stage

    def _resume(self, walks, requests, b, value) -> None:
        """Element b's sequence on, with `value` (the time its step reached), to its next request."""
        try:
            requests[b] = walks[b].send(value)
        except StopIteration:
            requests.pop(b, None)

    def _step(self, walks, requests, x, c, dd, every: bool):
        """One batched step of the elements asking to step (with `every`, of all: the others by zero),
        each sequence sent where its step ended; returns (x, the record of the first stage or None)."""
        asking = sorted(requests)
        rows = self.rows if every else asking
        t = self._times()[rows]
        end = t.copy()
        position = {b: i for i, b in enumerate(rows)}
        for b in asking:
            end[position[b]] = requests[b][1]
        x_rows, c_rows = (x, c) if every else (x[rows], None if c is None else c[rows])
        x_new, dx1, out1, last = self.step(rows, t, x_rows, self._step_lengths(rows, end), c_rows)
        natural = None
        if self.forcing is not None:
            natural, x_new = x_new, self._forced(end, x_new)
        self.counts["steps"] += 1
        self.stepping = _Stepping(position, x, dx1, x_new, x_new.detach().numpy(), c, dd, natural)
        self.cuts, self.signs = {}, {}
        for b in asking:
            self.t_grad.pop(b, None)
            self._resume(walks, requests, b, float(end[position[b]]))
        if self.cuts:
            index = torch.tensor(list(self.cuts))
            x_new = x_new.index_put((index,), torch.stack(list(self.cuts.values())))
        x = x_new if len(rows) == self.B else x.index_put((torch.tensor(rows),), x_new)
        first = self._record(x_rows, dx1, out1) if every or self.segments is not None else None
        if self.segments is not None:
            self._keep_segment(rows, t, end, first, x_new, dx1, out1, last)
        return x, first if every else None

    def _keep_segment(self, rows, t, planned_end, first, x_end, dx1, out1, last) -> None:
        """The records of a step at its start (after the events there) and at its end (before the
        events there: the last stage's derivatives and outputs, at the located time of a state event
        that cut the step linear between its first stage and the last)."""
        ended = np.array([self.elements[b].t for b in rows])
        planned = planned_end - t
        theta = torch.from_numpy(np.where(planned > 0.0, (ended - t) / np.where(planned > 0.0, planned, 1.0), 1.0))[:, None]
        dx_end = dx1 + theta * (last[0] - dx1)
        out_end = out1 + theta * (last[1] - out1)
        self.segments.append((list(rows), t, ended, first, self._record(x_end, dx_end, out_end)))

    def _interval_ends(self, k: int, first_stage: torch.Tensor, inner: list) -> torch.Tensor:
        """[B, C] each element's records at grid point k + 1 before its events (the end of its last
        step of the interval; an element standing still: its record at k); the intervals an event
        cut into several steps go into `inner` (see Trajectory)."""
        if len(self.segments) == 1:
            rows, t, ended, _, end = self.segments[0]
            if len(rows) == self.B and bool(np.all(ended > t)):
                return end
        steps = {b: [] for b in self.rows}
        for rows, t, ended, start, end in self.segments:
            for i, b in enumerate(rows):
                if ended[i] > t[i]:          # a step of length zero (a gradient's carrier) records nothing
                    steps[b].append((float(t[i] - self.t0[b]), float(ended[i] - self.t0[b]), start[i], end[i]))
        for b, kept in steps.items():
            if len(kept) > 1:
                inner.append((k, b, kept))
        return torch.stack([kept[-1][3] if kept else first_stage[b] for b, kept in steps.items()])

    def _step_lengths(self, rows, end: np.ndarray):
        """end - t per row: numpy, or a tensor [R, 1] where a located event time carries a gradient."""
        if not any(b in self.t_grad for b in rows):
            return end - self._times()[rows]
        return torch.stack([end[i] - self.t_grad[b] if b in self.t_grad else
                            torch.tensor(end[i] - self.elements[b].t, dtype=torch.float64)
                            for i, b in enumerate(rows)]).reshape(-1, 1)

    def _forced(self, t: np.ndarray, x: torch.Tensor) -> torch.Tensor:
        indices, values = self.forcing
        x = x.clone()
        x[:, indices] = torch.from_numpy(np.asarray(values(t), dtype=float).reshape(len(t), len(indices)))
        return x

    def _record(self, x, dx, out) -> torch.Tensor:
        return torch.cat([x, dx, out[:, self.n:]], dim=1).index_select(1, self.record_index)

    def _save_states(self, x: torch.Tensor, tau: float, final: bool = False) -> list[ElementStart]:
        """Every element's start at its current point, tau seconds into the run."""
        t, next_events = self._times(), [element.next_event for element in self.elements]
        if not self.snapshots:
            return self._replayable_states(t, next_events, x, tau, final)
        saved = []
        x_np = x.detach().numpy()
        for b, inst in enumerate(self.instances):
            self.ev.set_point(b, t[b], x_np[b], self._u(b, t[b]))
            state = inst.get_fmu_state()
            try:
                data = inst.serialize_fmu_state(state)
            finally:
                inst.free_fmu_state(state)
            saved.append(ElementStart(float(t[b]), data, float(next_events[b])))
        return saved

    def _replayable_states(self, t: np.ndarray, next_events, x: torch.Tensor, tau: float,
                           final: bool) -> list[ElementStart]:
        """Starts at the elements' current points for an FMU without saved states (see Replay); at
        the end of the run each keeps its element's instance, which the run leaves there."""
        parameters = {name: value.detach().clone() for name, value in self.topology.state_dict().items()}
        x_np = x.detach().numpy()
        saved = []
        for b, origin in enumerate(self.starts):
            recipe = Replay(origin, float(tau), parameters, self.h, "rk4" if self.rk4 else "euler",
                            self.inputs)
            start = ElementStart(float(t[b]), next_event_time=float(next_events[b]), replay=recipe)
            if final:
                self.ev.set_point(b, t[b], x_np[b], self._u(b, t[b]))
                self.model.hold(self.instances[b], start)
            saved.append(start)
        return saved

    # -- what each element's event sequence asks of the batch (see EventSequence) -------------
    def step_limit(self, element, limit):
        """The grid point, or a time event a rounding error past it: the element steps to the event's
        own time (and waits there) rather than jump from the grid point to it without a step."""
        return element.next_event if limit < element.next_event <= limit + element.tolerance(limit) else limit

    def indicators_at_end(self, element, t):
        b, step = element.index, self.stepping
        i = step.position[b]
        if step.natural is not None and element.z is not None:
            # Forced: an indicator the step's own course crossed fires where that course crossed it, the
            # step keeping its natural end. The forced end alone can hide a crossing: the VLDM's relay
            # switches inside a step, and the switch brings the speed error back under its threshold
            # by the end of the step the forcing copies (up to a fifth of a run's points in the wrong mode).
            # After such a cut the forced ends decide until a step ends without a crossing (else where
            # the natural and the forced end lie on either side of a threshold, the two alternate
            # without end: the VLDM's torque limit at 450.29 s of the extra loss's data).
            if b not in self.natural_cut:
                z = self.ev.indicators(b, t, step.natural[i].detach().numpy(), self._u(b, t))
                if crossed(element.z, z).any():
                    step.x_new[i] = step.natural[i]      # x_np shares its memory
                    self.natural_cut.add(b)
                    return z
            z = self.ev.indicators(b, t, step.x_np[i], self._u(b, t))
            if not crossed(element.z, z).any():
                self.natural_cut.discard(b)
            return z
        return self.ev.indicators(b, t, step.x_np[i], self._u(b, t))

    def completed_step(self, element, state_event):
        """fmi2CompletedIntegratorStep of the element at the end of its step: (step event, terminate)."""
        if not self.step_events:
            return False, False
        b = element.index
        if element.z is None or state_event:   # else the indicators left the instance there
            x_end = self.cuts[self.stepping.position[b]].detach().numpy() if state_event else \
                self.stepping.x_np[self.stepping.position[b]]
            self.ev.set_point(b, element.t, x_end, self._u(b, element.t))
        return self.instances[b].completed_integrator_step()

    stepped_on = None

    # -- events ------------------------------------------------------------------------------
    def _event_mode(self, b, t, x_minus: np.ndarray, grad: bool, signs=None, state_event: bool = False):
        """Event mode of element b at (t, x_minus) (with its linearisation if `grad`): its next time
        event, whether it terminates, and its indicators after the event as the next reference."""
        outcome = self.ev.handle_event(b, t, x_minus, self._u(b, t), self.sens if grad else None, signs,
                                       state_event)
        element = self.elements[b]
        element.next_event = outcome.next_event_time
        element.terminated |= outcome.terminate
        if element.z is not None:
            element.z = self.instances[b].get_event_indicators()
        return outcome

    def _events(self, rows, x, dd, c, signs=None, state_event: bool = False):
        """Event mode of the elements `rows` at their current points, batched; `signs` orients the
        perturbations of an element at a state event (see FmuEvaluator.handle_event)."""
        x_np = x.detach().numpy()
        grad = self.event_grad and self.ev.can_snapshot and x.requires_grad
        signs = signs or {}
        outcomes = {b: self._event_mode(b, self.elements[b].t, x_np[b], grad, signs.get(b), state_event)
                    for b in rows}
        if not grad:
            changed = [b for b, o in outcomes.items() if o.values_changed]
            if changed:  # a constant jump; x + 0 keeps the exact post-event values
                x_val = x_np.copy()
                for b in changed:
                    x_val[b] = outcomes[b].x_plus
                x = torch.from_numpy(x_val) + (x - x.detach()) if x.requires_grad else torch.from_numpy(x_val)
            return x, dd, c
        mask = np.zeros(self.B, dtype=bool)
        mask[[b for b, o in outcomes.items() if o.B is not None]] = True
        return self._linearised_event(x, self._known_deviation(x), outcomes, dd, c, mask)

    def _linearised_event(self, x, dev, outcomes: dict, dd, c, mask):
        """Post-event (x, dd, c) with the event linearisations of the elements in `outcomes`
        (see EventOutcome): x+ = x+_value + R dev + Rd dd,  dd+ = B dev + A dd,  c = G dd+."""
        B, n, K, Q = x.shape[0], self.n, self.n + self.ev.P, self.ev.carrier_width
        memory = self.ev.q > 0
        any_reset = any(o.values_changed for o in outcomes.values())
        if any_reset:      # the reset map (identity for the elements without a reset)
            x_val = x.detach().numpy().copy()
            R = np.tile(np.eye(n, K), (B, 1, 1))
        history = memory and dd is not None   # a carrier from earlier events exists
        Rd = np.zeros((B, n, Q)) if history else None
        A = np.zeros((B, Q, Q)) if history else None
        Bm = np.zeros((B, Q, K))
        G = np.zeros((B, self.ev.width, Q)) if memory else None
        any_rd = any_a = False
        for b, o in outcomes.items():
            if o.values_changed:
                x_val[b] = o.x_plus
                if o.R is not None:
                    R[b] = o.R
                if o.Rd is not None and Rd is not None:
                    Rd[b], any_rd = o.Rd, True
            if o.B is not None:
                Bm[b] = o.B
                if memory:
                    G[b] = o.G
                    if o.A is not None and A is not None:
                        A[b], any_a = o.A, True
        if any_reset:
            x = torch.from_numpy(x_val) + batch_matvec(R, dev)
            if any_rd:
                x = x + batch_matvec(Rd, dd)
        if not mask.any():
            return x, dd, c
        if memory and not (any_a or self.sens.memory_seen or self.sens.keep_shadows()):
            # memoryless so far: dd is not needed later, so c = (G B) dev directly
            c_new, dd_new = batch_matvec(np.matmul(G, Bm), dev), None
        else:
            dd_new = batch_matvec(Bm, dev)
            if any_a:
                dd_new = dd_new + batch_matvec(A, dd)
            c_new = batch_matvec(G, dd_new) if memory else dd_new
        if mask.all():
            return x, dd_new, c_new
        # elements without an event keep their carrier and correction (absent ones are zero)
        keep = torch.from_numpy(mask)[:, None]
        c = c_new if c is None else torch.where(keep, c_new, c)
        if dd_new is not None:
            dd = dd_new if dd is None else torch.where(keep, dd_new, dd)
        elif dd is not None:
            dd = dd.masked_fill(keep, 0.0)
        return x, dd, c

    def cut_at_state_event(self, element, t_k, t_new, z_new, tolerance):
        """The element's step from t_k to t_new cut at its earliest state event, located by the
        engine's root finder on the step's dense output (Euler: linear; RK4: cubic Hermite), beyond
        the crossing: (the located time, the indicators there). The state there, with the event
        time's gradient, becomes the step's end, and the perturbation signs are kept for the event."""
        b, step = element.index, self.stepping
        i, z_k = step.position[b], element.z
        x_k, dx1, x_new, h = step.x[b], step.dx1[i], step.x_new[i], t_new - t_k
        if self.rk4:
            f_new = self.rhs([b], np.array([t_new]), x_new[None], None if step.c is None else step.c[b:b + 1])[0][0]

        def dense(theta):
            return hermite(theta, h, x_k, dx1, x_new, f_new) if self.rk4 else x_k + theta * (x_new - x_k)

        def indicators_at(t):
            return self.ev.indicators(b, t, dense((t - t_k) / h).detach().numpy(), self._u(b, t))

        with torch.no_grad():
            t_hi, z_hi, fired, _ = locate(indicators_at, t_k, z_k, t_new, z_new, tolerance)
        # of several indicators firing at once, the steepest over the step carries the event time
        which = int(np.flatnonzero(fired)[np.argmax(np.abs(z_hi[fired] - z_k[fired]))])
        theta = (t_hi - t_k) / h
        t_star = t_k + theta * h
        self.cuts[i], t_e, self.signs[b] = self._pre_event_state(b, dense, theta, t_k, t_new, t_star, z_k, z_hi, which)
        if isinstance(t_e, torch.Tensor):
            self.t_grad[b] = t_e
            element.pending_step = True     # a step, of length zero at the limit, carries its gradient
        return t_star, z_hi

    def _pre_event_state(self, b, dense, theta, t_k, t_new, t_star, z_k, z_hi, j):
        """x(t_e) with t_e differentiable through the implicit-function correction (see module doc)."""
        h = t_new - t_k
        x_star = dense(theta)
        if not (self.event_grad and x_star.requires_grad):
            return x_star.detach(), t_star, None
        x_np = x_star.detach().numpy()
        gz, dz_dt = self.ev.indicator_gradient(b, t_star, x_np, j, self._u(b, t_star))
        eps = 1e-7
        with torch.no_grad():
            slope = ((dense(min(theta + eps, 1.0)) - dense(max(theta - eps, 0.0))) /
                     ((min(theta + eps, 1.0) - max(theta - eps, 0.0)) * h)).numpy()
        zdot = float(gz @ slope) + dz_dt
        if zdot == 0.0 or not math.isfinite(zdot):
            return x_star, t_star, None
        z_dev = (torch.from_numpy(gz) * (x_star - x_star.detach())).sum()
        dd = self.stepping.dd
        if dd is not None and self.ev.q:
            # the indicator may depend on the held discrete states too (the VLDM's start margin on
            # the held driver error): the event time moves with them
            gzd = self.ev.indicator_discrete_gradient(b, t_star, x_np, j, self._u(b, t_star))
            if gzd is not None:
                z_dev = z_dev + (torch.from_numpy(gzd) * dd[b]).sum()
        shift = -z_dev / zdot  # zero in value: the dense output is taken at exactly the located theta
        t_e = t_star + shift
        x_minus = dense(theta + shift / h)
        side = np.sign(z_hi[j]) if z_hi[j] != 0 else -np.sign(z_k[j])
        signs = np.ones(self.n + self.ev.P)
        signs[: self.n] = np.where(gz != 0, side * np.sign(gz), 1.0)
        return x_minus, t_e, signs

