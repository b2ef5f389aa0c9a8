"""A NeuralFMU as the engine's HybridSystem: forward simulation without torch in the loop.

`NeuralFmuSystem` is an `FmuSystem` whose derivatives pass through the topology in numpy, with the
weights of its fold (`Topology.folded`) frozen when the system is built: a few small matrix
products. The untrained hybrid (gate_ann = 0) returns the FMU's derivatives exactly.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from ..errors import FmuBuilderError
from ..simulation import SimulationResult, make_solver, output_grid, run
from ..simulation.core import SOURCE_DERIVATIVE, SOURCE_STATE, SOURCE_VARIABLE, Correction
from ..simulation.inputs import InputSignals
from ..simulation.system import FmuSystem
from .model import NeuralFMU
from .topology import Topology


def _sigmoid(z, out):
    np.multiply(z, 0.5, out=out)
    np.tanh(out, out=out)
    np.multiply(out, 0.5, out=out)
    return np.add(out, 0.5, out=out)


_ACTIVATIONS = {torch.tanh: np.tanh, torch.relu: lambda z, out: np.maximum(z, 0.0, out=out), torch.sigmoid: _sigmoid}
_ACTIVATION_NAMES = {torch.tanh: "tanh", torch.relu: "relu", torch.sigmoid: "sigmoid"}


_EMPTY = np.zeros(0)


class NumpyTopology:
    """The topology's forward pass in numpy (see the module docstring). The last layer has no
    activation (build_ann), so it is applied separately."""

    def __init__(self, topology: Topology):
        self.n = topology.n_states
        self.channels = np.array(topology.channel_index, dtype=int)
        self.source = topology.input_source.numpy().copy()
        self.gate_fmu = topology.gate_fmu.detach().numpy().copy()
        self.active = topology.ann is not None and bool(topology.gate_ann.count_nonzero())
        self.layers = []
        if not self.active:
            return
        # A base term (base_term.py) is added to the network's output, through the ANN gate.
        self._base = topology.base.numpy_kernel() if topology.base is not None else None
        self._base_at = topology.base.point_kernel() if topology.base is not None else None
        self._base_gate = topology.gate_ann.detach().numpy().copy()
        self._base_terms = topology.base.terms_by_basis() if topology.base is not None else None
        with torch.no_grad():
            folded = topology.folded()
            for layer in folded:   # the torch topology's own fold, as numpy arrays
                self.layers.append(tuple(a.numpy().copy() for a in layer) if isinstance(layer, tuple)
                                   else _ACTIVATIONS[layer])
        # The same layers for the compiled core: (W, b, the activation after them or None).
        self.program = [(layer[0], layer[1], _ACTIVATION_NAMES[folded[i + 1]]
                         if i + 1 < len(folded) and not isinstance(folded[i + 1], tuple) else None)
                        for i, layer in enumerate(self.layers) if isinstance(layer, tuple)]

        # Preallocated buffers; the inputs are gathered one by one (a handful of scalars is faster
        # than fancy indexing), the last layer of a single channel is a dot product.
        n = self.n
        self._gather = [(0, i) if i < n else (1, i - n) if i < 2 * n else (2, i - 2 * n) for i in self.source]
        self._z = np.empty(len(self.source))
        self._hidden, last = [], None
        for i, layer in enumerate(self.layers):
            if isinstance(layer, tuple):
                act = self.layers[i + 1] if i + 1 < len(self.layers) and not isinstance(self.layers[i + 1], tuple) else None
                last = (layer[0], layer[1], act, np.empty(layer[0].shape[0]))
                self._hidden.append(last)
        self._hidden.pop()
        self._last_W, self._last_b = last[0], last[1]
        single = len(self.channels) == 1
        self._single_channel = int(self.channels[0]) if single else None
        self._single_gate = float(self.gate_fmu[0]) if single else None
        self._single_row = self._last_W[0].copy() if single else None

    def __call__(self, x: np.ndarray, der: np.ndarray, variables: np.ndarray) -> np.ndarray:
        """Hybrid derivatives from the state, the FMU's derivatives and the FMU variables it needs.
        `der` is updated in place and returned."""
        if not self.active:
            return der
        z = self._z
        sources = (x, der, variables)
        for j, (kind, index) in enumerate(self._gather):
            z[j] = sources[kind][index]
        base = 0.0 if self._base_at is None else self._base_gate[0] * self._base_at(z)
        dot, add = np.dot, np.add
        for W, b, act, out in self._hidden:
            dot(W, z, out=out)
            add(out, b, out=out)
            if act is not None:
                act(out, out=out)
            z = out
        c = self._single_channel
        if c is not None:
            der[c] = dot(self._single_row, z) + self._last_b[0] + self._single_gate * der[c] + base
        else:
            der[self.channels] = self._last_W @ z + self._last_b + self.gate_fmu * der[self.channels]
        return der

    def correction(self, variable_vrs: list[int]) -> Correction | None:
        """The same map for the compiled core (simulation.core.Correction); None when inactive."""
        if not self.active:
            return None
        sources = (SOURCE_STATE, SOURCE_DERIVATIVE, SOURCE_VARIABLE)
        terms, bias, gate = [], 0.0, 0.0
        if self._base_terms is not None:
            terms, bias = self._base_terms
            gate = float(self._base_gate[0])
        return Correction(inputs=[(sources[kind], index) for kind, index in self._gather], variable_vrs=variable_vrs,
                          layers=self.program, channels=self.channels.tolist(), gate_fmu=self.gate_fmu,
                          terms=terms, term_bias=bias, term_gate=gate)

    def rows(self, x: np.ndarray, der: np.ndarray, variables: np.ndarray) -> np.ndarray:
        """The same for several points at once: x, der [R, n], variables [R, k]; `der` is updated
        in place and returned."""
        if not self.active:
            return der
        z = np.concatenate((x, der, variables), axis=1)[:, self.source]
        base = 0.0 if self._base is None else self._base_gate[0] * self._base(z)[:, None]
        for layer in self.layers:
            if isinstance(layer, tuple):
                z = z @ layer[0].T + layer[1]
            else:
                layer(z, z)
        der[:, self.channels] = z + base + self.gate_fmu * der[:, self.channels]
        return der


class NeuralFmuSystem(FmuSystem):
    """The engine's HybridSystem for a NeuralFMU (see the module docstring). Recorded derivative
    names (der(x)) report the hybrid derivatives."""

    def __init__(self, model: NeuralFMU, *, variables: Sequence[str], start_values: dict | None = None,
                 inputs: InputSignals | None = None, tolerance: float | None = None):
        values = {**model.start_values_with_parameters(), **(start_values or {})}
        super().__init__(model.loaded_copy(), variables=variables, start_values=values, inputs=inputs, tolerance=tolerance)
        self.kernel = NumpyTopology(model.topology)
        info = model.info
        self._variable_vrs = [info.variable(name).value_reference for name in model.topology.fmu_variables]
        self._read_variables = self.instance.real_getter(self._variable_vrs)
        self._has_variables = bool(model.topology.fmu_variables)
        derivative_names = [v.name for v in info.derivatives]
        self._derivative_columns = [(j, derivative_names.index(name)) for j, name in enumerate(self.output_names)
                                    if name in derivative_names]

    def compiled_correction(self) -> Correction | None:
        return self.kernel.correction(self._variable_vrs)

    def derivatives(self, t: float, x: np.ndarray) -> np.ndarray:
        return self._add_network(super().derivatives(t, x), x)

    def _add_network(self, der: np.ndarray, x: np.ndarray) -> np.ndarray:
        kernel = self.kernel
        if not kernel.active:
            return der
        return kernel(x, der, self._read_variables() if self._has_variables else _EMPTY)

    def outputs(self, times: np.ndarray, states: np.ndarray) -> np.ndarray:
        table = super().outputs(times, states)
        if self._derivative_columns and self.kernel.active:
            for row, t in enumerate(times):
                # In event mode (e.g. the FMU asked to terminate) it already holds (t, x) and
                # refuses fmi2SetContinuousStates.
                dx = self.derivatives(float(t), states[row]) if self._continuous_mode \
                    else self._add_network(self._get_dx(), states[row])
                for column, i in self._derivative_columns:
                    table[row, column] = dx[i]
        return table


def simulate_hybrid(model: NeuralFMU, *, start_time: float, stop_time: float, variables: Sequence[str],
                    solver: str = "euler", step_size: float | None = None, output_interval: float | None = None,
                    inputs: InputSignals | None = None, rtol: float = 1e-6,
                    record_events: bool = False) -> SimulationResult:
    """Forward simulation of a NeuralFMU with fmubuilder's engine (numpy, no gradients);
    record_events adds rows just before and after each event."""
    if not stop_time > start_time:
        raise FmuBuilderError(f"stop time {stop_time:g} is not after start time {start_time:g}")
    adaptive = solver == "dopri5"
    if not adaptive and not step_size:
        raise FmuBuilderError(f"the fixed-step solver '{solver}' needs a step size")
    integrator = make_solver(solver, rtol=rtol, atol=1e-8, max_step=step_size or (stop_time - start_time) / 50) \
        if adaptive else make_solver(solver, step_size=step_size)
    system = NeuralFmuSystem(model, variables=variables, inputs=inputs, tolerance=rtol if adaptive else None)
    try:
        interval = output_interval or step_size or (stop_time - start_time) / 500
        return run(system, integrator, start_time=start_time, stop_time=stop_time,
                   output_times=output_grid(start_time, stop_time, interval), record_events=record_events)
    finally:
        system.close()
