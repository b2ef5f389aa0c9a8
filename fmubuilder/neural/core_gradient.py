"""The training's simulations in the compiled core: with the gradient (core/sensitivity.c) where
it is exact, and without it (`simulate_without_gradient`: starts captured, losses without
gradient, the warm start's trials) wherever the core runs the model at all.

`simulate_for_loss` is `solve.simulate` for a loss evaluation: where the core's gradient is exact
it runs each element in C and returns a Trajectory whose records are a torch.autograd.Function of
the folded network (Topology.folded: each layer's W and b, and the FMU gates), so the loss is
defined in torch as before and autograd carries the gradient on to the topology's parameters. The
backward pass runs each element again in C with forward sensitivities S = dx/dtheta stepped beside
the states in the solver's own stages (the FMU's Jacobian by forward differences, the network's
by backpropagation), summing grad . d(record)/dtheta over the records. One C run forward, one with
sensitivities backward; no autograd graph per step.

The records are the torch solver's: each grid point after its events and, with RK4, before them.
At a step's end the core reads a derivative or an FMU variable at the step's end where the torch
solver takes RK4's last stage, as the scoring's engine does; the two losses differ by about 1e-4
of the loss on the DC drive (tests/neural/test_core_gradient.py).

The core's gradient follows the states through steps and passes them through events unchanged, so
it is used where the modelDescription says that is all there is (`exact_in_core`): no event
indicators (a state event would need the event time's term), no discrete variables (a sampled
controller's held values need solve.py's discrete-state path, item 3 of its docstring: on the VLDM
the core's gradient without it is several times too small, benchmarks/bench_gradient_core.py), no
discrete inputs, no trained FMU parameters, and an FMU that saves its state (the element starts).
Time events of the FMU's own (the DC drive's set-point profile) pass, on a grid point or between
two (the core records both sides of each, which give the torch solver's steps of a cut interval).
A run in which an event resets the states is done again by the torch solver, and that model stays
with it. A discrete state the
modelDescription does not declare cannot be seen; the rule trusts the declaration.
"""
from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import numpy as np
import torch

from ..simulation import core, make_solver
from ..simulation.system import _OutputColumns
from .model import NeuralFMU
from .solve import SOLVERS, ElementStart, Trajectory, can_snapshot, simulate

_ACTIVATIONS = {torch.tanh: "tanh", torch.sigmoid: "sigmoid", torch.relu: "relu"}
# Models with a run in which an event reset the states (see the module docstring): torch from then on.
_RESETTING: "weakref.WeakSet[NeuralFMU]" = weakref.WeakSet()


def exact_in_core(model: NeuralFMU) -> bool:
    """Whether the core's gradient is the exact gradient of this model's runs, from its
    modelDescription and topology (see the module docstring)."""
    info = model.info
    internal_discrete = any(v.variability == "discrete" and v.causality in ("local", "output")
                            for v in info.variables.values())
    return runs_in_core(model) and info.n_event_indicators == 0 and not internal_discrete


def runs_in_core(model: NeuralFMU) -> bool:
    """Whether the core runs this model's simulations without gradient: the network in the loop and
    the FMU's events as the engine handles them (state events and discrete states included), from
    element starts the FMU saves; trained FMU parameters and discrete inputs stay with torch."""
    info = model.info
    discrete_inputs = any(v.variability == "discrete" or v.api_type != "Real" for v in info.inputs)
    return (model.topology.ann is not None and not discrete_inputs and not model.config.parameters
            and can_snapshot(info) and core.enabled())


def simulate_for_loss(model: NeuralFMU, duration: float, step_size: float, *, starts, record, solver: str,
                      inputs=None, keep_final_state: bool = False) -> Trajectory:
    """solve.simulate for a loss evaluation: in the core where its gradient is exact, else torch."""
    if not torch.is_grad_enabled():
        return simulate_without_gradient(model, duration, step_size, starts=starts, record=record, solver=solver,
                                         inputs=inputs, keep_final_state=keep_final_state)
    usable = (solver in SOLVERS and model not in _RESETTING and exact_in_core(model)
              and all(start.fmu_state is not None for start in starts))
    if usable:
        trajectory = CoreElements(model, duration, step_size, starts, record, solver, inputs).trajectory(
            keep_final_state)
        if trajectory is not None:
            return trajectory
        _RESETTING.add(model)
    return simulate(model, duration, step_size, starts=starts, record=record, solver=solver, inputs=inputs,
                    keep_final_state=keep_final_state)


def simulate_without_gradient(model: NeuralFMU, duration: float, step_size: float, *, starts, record,
                              solver: str, inputs=None, keep_final_state: bool = False, capture=()) -> Trajectory:
    """solve.simulate without gradient: each element one run in the core where it runs the model
    (`capture`, for one element: its run split at those grid points, each piece's end saved),
    else the torch solver. A fresh start is first saved by the torch solver, one step's work."""
    starts = list(starts)
    if solver not in SOLVERS or not runs_in_core(model) or (capture and len(starts) != 1):
        with torch.no_grad():
            return simulate(model, duration, step_size, starts=starts, record=record, solver=solver, inputs=inputs,
                            keep_final_state=keep_final_state, capture=capture)
    with torch.no_grad():
        starts = [start if start.fmu_state is not None else _saved_fresh(model, start, step_size, solver, inputs)
                  for start in starts]
        pieces = _pieces(duration, step_size, capture)
        runs, piece_starts = [], starts
        for offset, length in pieces:
            trajectory = CoreElements(model, length, step_size, piece_starts, record, solver, inputs,
                                      strict=False).trajectory(keep_final_state or len(pieces) > 1)
            if trajectory is None:      # rows the core did not record (a run the model ended early)
                return simulate(model, duration, step_size, starts=starts, record=record, solver=solver,
                                inputs=inputs, keep_final_state=keep_final_state, capture=capture)
            runs.append((offset, piece_starts, trajectory))
            piece_starts = trajectory.final_starts
    return _joined(runs, step_size, set(capture))


def _saved_fresh(model: NeuralFMU, start: ElementStart, step_size: float, solver: str, inputs) -> ElementStart:
    return simulate(model, step_size, step_size, starts=[start], solver=solver, inputs=inputs,
                    capture=[0]).captured[0][0]


def _pieces(duration: float, step_size: float, capture) -> list[tuple[int, float]]:
    """(first grid index, duration) of the runs between the captured grid points."""
    K = max(1, int(math.ceil(duration / step_size - 1e-9)))
    cuts = sorted({0, *(k for k in capture if 0 < k < K)})
    ends = [*cuts[1:], K]
    return [(a, (b - a) * step_size if b < K else duration - a * step_size) for a, b in zip(cuts, ends)]


def _joined(runs: list, step_size: float, capture: set) -> Trajectory:
    """One Trajectory of the pieces of a run split at grid points (see simulate_without_gradient)."""
    first, last = runs[0][2], runs[-1][2]
    if len(runs) == 1 and not capture:
        return first
    times = np.concatenate([first.times] + [offset * step_size + t.times[1:] for offset, _, t in runs[1:]])
    times[-1] = runs[-1][0] * step_size + last.times[-1]
    values = torch.cat([first.values] + [t.values[1:] for _, _, t in runs[1:]])
    before = torch.cat([t.before for _, _, t in runs]) if first.before is not None else None
    inner = [(k + offset, b, [(a + offset * step_size, e + offset * step_size, *rows) for a, e, *rows in steps])
             for offset, _, t in runs for k, b, steps in t.inner]
    captured = {offset: starts for offset, starts, _ in runs if offset in capture}
    K = len(times) - 1
    if K in capture:
        captured[K] = last.final_starts
    return Trajectory(times=times, t0=first.t0, names=first.names, values=values, final_states=last.final_states,
                      final_starts=last.final_starts, captured=captured, before=before, inner=inner,
                      stats={"core_gradient": True})


class CoreElements:
    """Batch elements run one after another in the core, forward and with sensitivities."""

    def __init__(self, model: NeuralFMU, duration: float, step_size: float, starts, record, solver: str, inputs,
                 strict: bool = True):
        self.strict = strict    # False (for measurements): state resets let pass
        self.model, self.starts, self.record, self.inputs = model, list(starts), list(record), inputs
        self.solver = make_solver(solver, step_size=step_size)
        K = max(1, int(math.ceil(duration / step_size - 1e-9)))
        self.grid = np.minimum(np.arange(K + 1) * step_size, duration)
        self.grid[-1] = duration
        self.rk4 = solver == "rk4"
        self.layers = model.topology.folded()
        self.theta = [tensor for layer in self.layers if isinstance(layer, tuple) for tensor in layer]
        self.theta.append(model.topology.gate_fmu)
        self.n_parameters = sum(t.numel() for t in self.theta)
        self.instances = None

    def trajectory(self, keep_final_state: bool) -> Trajectory | None:
        """The elements' Trajectory with records differentiable through the core; None where a run
        reset the states (see the module docstring)."""
        runs = self._forward(keep_final_state)
        if runs is None:
            return None
        rows = _CoreRuns.apply(self, *self.theta)
        rows = (rows,) if isinstance(rows, torch.Tensor) else rows
        values = torch.stack([r[layout.grid] for r, layout in zip(rows, self.layouts)], dim=1)
        before = torch.stack([r[layout.ends] for r, layout in zip(rows, self.layouts)], dim=1)
        inner = [(k, b, [(start, end, rows[b][first], rows[b][last]) for start, end, first, last in steps])
                 for b, layout in enumerate(self.layouts) for k, steps in sorted(layout.inner.items())]
        finals = torch.from_numpy(np.stack([run.x for run in runs]))
        return Trajectory(times=self.grid.copy(), t0=np.array([s.t0 for s in self.starts], dtype=float),
                          names=list(self.record), values=values, final_states=finals,
                          final_starts=self._final_starts if keep_final_state else None,
                          before=before if self.rk4 else None, inner=inner if self.rk4 else [],
                          stats={"core_gradient": True})

    # -- the runs ---------------------------------------------------------------------------------
    def _forward(self, keep_final_state: bool):
        """Each element's run in the core, its events' rows recorded (see _layout); None if an event
        reset the states."""
        self.instances = self.model.instances_for(self.starts)
        self.correction = self._correction()
        runs, finals, self.layouts = [], [], []
        for b, start in enumerate(self.starts):
            run, _, resets = self._run(b, None)
            layout = None if self.strict and (resets or run.terminated) else _layout(run, start.t0, self.grid)
            if layout is None:
                return None
            runs.append(run)
            self.layouts.append(layout)
            if keep_final_state:
                finals.append(self._saved(b, run))
        self.tables = [run.table for run in runs]
        self._final_starts = finals
        return runs

    def gradient(self, grads: list) -> np.ndarray:
        """The sum over elements, recorded rows and columns of grads[b][row, column] d(record)/dtheta."""
        total = np.zeros(self.n_parameters)
        for b, weights in enumerate(grads):
            if weights is not None and np.any(weights):
                total += self._run(b, weights)[1]
        return total

    def _run(self, b: int, weights):
        start = self.starts[b]
        system = _ElementSystem(self.instances[b], self.model, self.record, self.inputs, self.correction)
        x0 = self._placed(system.instance, start)
        return core.run_with_gradient(system, self.solver, start_time=start.t0, stop_time=start.t0 + self.grid[-1],
                                      output_times=start.t0 + self.grid, x0=x0, next_event=start.next_event_time,
                                      n_parameters=self.n_parameters, weights=weights, record_events=True)

    def _placed(self, instance, start: ElementStart) -> np.ndarray:
        """The instance at the element's start (its saved FMU state, the state overrides); its states."""
        state = instance.deserialize_fmu_state(start.fmu_state)
        try:
            instance.set_fmu_state(state)
        finally:
            instance.free_fmu_state(state)
        x = instance.get_continuous_states()
        if start.states:
            names = self.model.state_names()
            for name, value in start.states.items():
                x[names.index(name)] = float(value)
            instance.set_continuous_states(x)
        return x

    def _saved(self, b: int, run) -> ElementStart:
        instance = self.instances[b]
        instance.set_time(run.t)
        if self.inputs is not None and self.inputs.continuous:
            instance.set_real([v.value_reference for v in self.inputs.continuous], self.inputs.at(run.t))
        instance.set_continuous_states(run.x)
        state = instance.get_fmu_state()
        try:
            data = instance.serialize_fmu_state(state)
        finally:
            instance.free_fmu_state(state)
        return ElementStart(float(run.t), data, float(run.next_event))

    def _correction(self) -> core.Correction:
        """The folded network as the core evaluates it, with the base term (see NumpyTopology)."""
        topology, n = self.model.topology, self.model.info.n_states
        sources = [(core.SOURCE_STATE, i) if i < n else (core.SOURCE_DERIVATIVE, i - n) if i < 2 * n
                   else (core.SOURCE_VARIABLE, i - 2 * n) for i in topology.input_source.tolist()]
        program = []
        for i, layer in enumerate(self.layers):
            if isinstance(layer, tuple):
                following = self.layers[i + 1] if i + 1 < len(self.layers) else None
                activation = None if following is None or isinstance(following, tuple) else _ACTIVATIONS[following]
                program.append((layer[0].detach().numpy().copy(), layer[1].detach().numpy().copy(), activation))
        terms, bias, gate = [], 0.0, 0.0
        if topology.base is not None:
            terms, bias = topology.base.terms_by_basis()
            gate = float(topology.gate_ann[0])
        info = self.model.info
        return core.Correction(inputs=sources, variable_vrs=[info.variable(name).value_reference
                                                             for name in topology.fmu_variables],
                               layers=program, channels=list(topology.channel_index),
                               gate_fmu=topology.gate_fmu.detach().numpy().copy(), terms=terms, term_bias=bias,
                               term_gate=gate)


class _ElementSystem:
    """What the core reads of a system (see core._plan), around an instance at an element start."""

    def __init__(self, instance, model: NeuralFMU, record, inputs, correction):
        info = model.info
        self.instance, self.info = instance, info
        self.n_states, self.n_indicators = info.n_states, info.n_event_indicators
        self.recorded = [info.variable(name) for name in record]
        self.columns = _OutputColumns(instance, info, self.recorded)
        self.inputs = inputs
        self.breakpoints = inputs.breakpoints if inputs is not None else np.zeros(0)
        self.input_event_times = inputs.discrete_change_times().tolist() if inputs is not None else []
        self._correction = correction

    def compiled_correction(self):
        return self._correction


def _event_rows(times: np.ndarray, events: np.ndarray) -> np.ndarray | None:
    """The row before each event: rows at one time (an event's exact time) start with its events'
    pairs (before, after), one after the other; a grid record there follows them. None if the
    rows do not hold every event's pair."""
    starts = np.flatnonzero(np.r_[True, times[1:] != times[:-1]])     # runs of equal times
    lengths = np.diff(np.r_[starts, times.size])
    event_times, counts = np.unique(events, return_counts=True)
    at = np.clip(np.searchsorted(event_times, times[starts]), 0, max(len(event_times) - 1, 0))
    pairs = np.where(event_times[at] == times[starts], counts[at], 0) if events.size else np.zeros_like(starts)
    if pairs.sum() != events.size or np.any(2 * pairs > lengths):
        return None
    first = np.repeat(starts, pairs)
    nth = np.arange(events.size) - np.repeat(np.cumsum(pairs) - pairs, pairs)
    return first + 2 * nth


@dataclass
class _Layout:
    """Where one run's records are among the rows the core recorded: each event gives a row before
    it and one after it, at its time; each grid point its record after its events."""
    grid: np.ndarray        # [K+1] the row of each grid point's record
    ends: np.ndarray        # [K] the row of grid point k + 1 before its events (an interval's end)
    inner: dict             # {k: [(start, end, row at the start, row at the end before its events)]}:
                            # the steps of a grid interval that events cut, times from the run's start


def _layout(run, t0: float, grid: np.ndarray) -> _Layout | None:
    """The run's _Layout, as the torch solver's Trajectory records it; None if rows are missing."""
    times, events = np.asarray(run.times, dtype=float), np.array([t for t, _ in run.events], dtype=float)
    before = _event_rows(times, events)
    if before is None:
        return None
    is_grid = np.ones(times.size, dtype=bool)
    is_grid[before] = is_grid[before + 1] = False
    grid_rows = np.flatnonzero(is_grid)
    if len(grid_rows) != len(grid):
        return None
    grid_times = t0 + grid
    tolerance = 1e-9 * max(1.0, float(np.max(np.abs(grid_times))))
    nearest = np.clip(np.searchsorted(grid_times, events), 1, len(grid_times) - 1)
    nearest -= (events - grid_times[nearest - 1]) < (grid_times[nearest] - events)
    on_grid = np.abs(grid_times[nearest] - events) <= tolerance
    ends = grid_rows[1:].copy()
    # the first event at a grid point: the value before them all ends the interval before it
    points, first = np.unique(nearest[on_grid], return_index=True)
    inside = points > 0
    ends[points[inside] - 1] = before[on_grid][first[inside]]
    cuts = {}
    for t, row in zip(events[~on_grid].tolist(), before[~on_grid].tolist()):
        cuts.setdefault(int(np.searchsorted(grid_times, t)) - 1, []).append((t, row, row + 1))
    ends = ends.tolist()
    inner = {k: _steps(k, cut, grid_times, grid_rows, ends, t0) for k, cut in cuts.items()}
    return _Layout(grid_rows, np.array(ends, dtype=int), inner)


def _steps(k: int, cut: list, grid_times: np.ndarray, grid_rows: list, ends: list, t0: float) -> list:
    """The steps of grid interval k between the events inside it (several at one time: the row
    before the first, after the last)."""
    steps, start, first = [], grid_times[k], grid_rows[k]
    for index, (t, before, after) in enumerate(cut):
        if index + 1 < len(cut) and cut[index + 1][0] == t:
            continue
        same = [entry for entry in cut if entry[0] == t]
        steps.append((start - t0, t - t0, first, same[0][1]))
        start, first = t, after
    steps.append((start - t0, grid_times[k + 1] - t0, first, ends[k]))
    return steps


class _CoreRuns(torch.autograd.Function):
    """Each element's recorded rows [rows, C] (see _Layout) as a function of theta (CoreElements.theta)."""

    @staticmethod
    def forward(ctx, elements: CoreElements, *theta):
        ctx.elements = elements
        return tuple(torch.from_numpy(table) for table in elements.tables)

    @staticmethod
    def backward(ctx, *grads):
        elements = ctx.elements
        flat = elements.gradient([None if g is None else g.detach().numpy() for g in grads])
        grads, offset = [], 0
        for tensor in elements.theta:
            grads.append(torch.from_numpy(flat[offset:offset + tensor.numel()].reshape(tensor.shape).copy()))
            offset += tensor.numel()
        return (None, *grads)
