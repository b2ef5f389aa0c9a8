"""The hybrid model computed in Python: the original FMU plus onnxruntime.

`HybridReference` is a `HybridSystem` for the simulation engine that evaluates exactly what
the exported FMU evaluates in C (see spec.py for the formula), but from independent parts:
the original FMU's binary for f, and onnxruntime on the ONNX file for the network (the FMU
uses the C kernel generated from that file). Validation compares the two.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from fmubuilder.fmi.instance import Fmu
from fmubuilder.simulation.system import FmuSystem, values_reader

from .network import OnnxNetwork
from .spec import HybridSpec


def hybrid_value(p_fmu: float, f: float, p_ann: float, ann: float) -> float:
    """p_fmu * f + p_ann * ann where a zero gate drops its term, in the wrapper's order."""
    value = p_fmu * f if p_fmu != 0.0 else 0.0
    if p_ann != 0.0:
        value = value + p_ann * ann
    return value


class HybridReference(FmuSystem):
    """The hybrid model as a HybridSystem: the original FMU with corrected derivatives.

    `fmu` is the loaded original FMU; `p_ann`/`p_fmu` override the spec's gate values.
    Recorded `variables` may include the channels' der(x) and the spec's aliases of them: they
    are recorded as hybrid values.
    """

    def __init__(self, fmu: Fmu, spec: HybridSpec, *, variables: Sequence[str], start_values: dict | None = None,
                 inputs=None, tolerance: float | None = None, p_ann: Sequence[float] | None = None,
                 p_fmu: Sequence[float] | None = None):
        super().__init__(fmu, variables=variables, start_values=start_values, inputs=inputs, tolerance=tolerance)
        info = fmu.info
        self.network = OnnxNetwork(spec.onnx) if spec.channels else None
        self.p_ann = [float(g) for g in (p_ann if p_ann is not None else spec.p_ann)]
        self.p_fmu = [float(g) for g in (p_fmu if p_fmu is not None else spec.p_fmu)]
        self.channel_index = [info.state_index(c) for c in spec.channels]
        self._read_inputs = values_reader(self.instance, [info.variable(name) for name in spec.inputs])
        self._channel_columns = [(j, spec.channels.index(name)) for j, name in enumerate(self.output_names)
                                 if name in spec.channels]
        self._alias_columns = [(j, spec.channels.index(spec.aliases[name])) for j, name in enumerate(self.output_names)
                               if name in spec.aliases]

    def derivatives(self, t: float, x: np.ndarray) -> np.ndarray:
        if not any(g != 0.0 for g in self.p_ann):
            return self._hybrid(super().derivatives(t, x))
        # The network's inputs before the original's derivatives: a lazily evaluating FMU may
        # return, after fmi2GetDerivatives, outputs of the previous point (OpenModelica 1.18).
        self._at(t, x)
        ann = self.network_output()
        return self._hybrid(self.instance.get_derivatives(), ann)

    def outputs(self, times: np.ndarray, states: np.ndarray) -> np.ndarray:
        table = super().outputs(times, states)
        for row, (t, x) in enumerate(zip(times, states)) if self._channel_columns or self._alias_columns else ():
            if self._continuous_mode:   # in event mode the FMU already holds (t, x)
                self._at(t, x)
            ann = self._network_if_gated()
            dx = self._hybrid(self.instance.get_derivatives(), ann)
            for column, c in self._channel_columns:
                table[row, column] = dx[self.channel_index[c]]
            # An alias holds the original's der(x): corrected like der(x), from its own value.
            for column, c in self._alias_columns:
                table[row, column] = hybrid_value(self.p_fmu[c], float(table[row, column]), self.p_ann[c],
                                                  float(ann[c]) if ann is not None else 0.0)
        return table

    def network_output(self) -> np.ndarray:
        """The network's output at the FMU's current point."""
        return self.network(self._read_inputs())

    def _network_if_gated(self) -> np.ndarray | None:
        return self.network_output() if any(g != 0.0 for g in self.p_ann) else None

    def _hybrid(self, dx: np.ndarray, ann: np.ndarray | None = None) -> np.ndarray:
        """The corrected derivatives; `ann` is the network output at this point if known."""
        dx = np.array(dx, dtype=float)
        if ann is None:
            ann = self._network_if_gated()
        for c, i in enumerate(self.channel_index):
            dx[i] = hybrid_value(self.p_fmu[c], float(dx[i]), self.p_ann[c], float(ann[c]) if ann is not None else 0.0)
        return dx
