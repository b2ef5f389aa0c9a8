"""A fitted term as a fixed part of a NeuralFMU's correction: the ANN learns what the term leaves.

A term is a sum over `terms` (the diagnosis' fitted term: {"variable", "basis", "center",
"coefficient"}, basis one of 1, w, |w|, w*|w|, w^2) of coefficient * basis(variable - center).
`FittedTerm` evaluates it in torch with the operators the exported C kernel supports (MatMul, Sub,
Abs, Mul, Add), so that a correction `term + ANN` freezes to one ONNX graph; `term_values` is the
same in numpy for the engine.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import nn

from ..errors import FmuBuilderError
from ..simulation.core import BASES   # the compiled core's forms, in its order (terms_by_basis)

DTYPE = torch.float64


def term_inputs(terms: list[dict]) -> list[str]:
    """The variables a term reads, in order of first appearance."""
    return list(dict.fromkeys(t["variable"] for t in terms if t["basis"] != "1"))


class FittedTerm(nn.Module):
    """sum_k coefficient_k * basis_k(w_k - center_k) over the terms, for inputs u [B, len(inputs)]:
    each term gets its own column w_k = u @ select_k, since one variable may appear with different
    centers. Output [B, 1]."""

    def __init__(self, terms: list[dict], inputs: list[str]):
        super().__init__()
        variable_terms = [t for t in terms if t["basis"] != "1"]
        count = max(len(variable_terms), 1)
        self.register_buffer("select", torch.zeros(len(inputs), count, dtype=DTYPE))
        self.register_buffer("center", torch.zeros(count, dtype=DTYPE))
        self.register_buffer("weights", torch.zeros(len(BASES), count, 1, dtype=DTYPE))
        self.register_buffer("bias", torch.tensor([sum(float(t["coefficient"]) for t in terms if t["basis"] == "1")],
                                                  dtype=DTYPE))
        for k, term in enumerate(variable_terms):
            if term["basis"] not in BASES:
                raise FmuBuilderError(f"cannot export the term form {term['basis']!r}")
            if term["variable"] not in inputs:
                raise FmuBuilderError(f"the term reads '{term['variable']}', which is not among the inputs {inputs}")
            self.select[inputs.index(term["variable"]), k] = 1.0
            self.center[k] = float(term["center"])
            self.weights[BASES.index(term["basis"]), k, 0] = float(term["coefficient"])
        self.used = [b for b in range(len(BASES)) if bool(self.weights[b].any())]

    def forward(self, u):
        w = u @ self.select - self.center
        out = self.bias
        for b in self.used:
            phi = (w, torch.abs(w), w * torch.abs(w), w * w)[b]
            out = out + phi @ self.weights[b]
        return out

    def point_kernel(self):
        """The same function at one point, u [n_in] -> a float, in Python floats: the engine calls it
        at every stage of every step, where numpy's overhead per call (4.5 us) is most of the cost.
        Summed per basis, then the bases in order, as numpy_kernel sums (the same to the bit when
        each basis has one term)."""
        used = [[(int(self.select[:, k].argmax()), float(self.center[k]), float(self.weights[b, k, 0]))
                 for k in range(self.center.numel()) if float(self.weights[b, k, 0]) != 0.0]
                for b in range(len(BASES))]
        bias = float(self.bias[0])
        w_terms, abs_terms, signed_square_terms, square_terms = used

        def evaluate(u) -> float:
            total = bias
            total += sum(c * (float(u[i]) - m) for i, m, c in w_terms)
            total += sum(c * abs(float(u[i]) - m) for i, m, c in abs_terms)
            total += sum(c * ((float(u[i]) - m) * abs(float(u[i]) - m)) for i, m, c in signed_square_terms)
            total += sum(c * ((float(u[i]) - m) * (float(u[i]) - m)) for i, m, c in square_terms)
            return total
        return evaluate

    def terms_by_basis(self) -> tuple[list[tuple[int, int, float, float]], float]:
        """([(basis index in BASES, input index, center, coefficient)] grouped by basis, bias): the
        terms point_kernel sums, in its order, for the compiled core."""
        terms = [(b, int(self.select[:, k].argmax()), float(self.center[k]), float(self.weights[b, k, 0]))
                 for b in range(len(BASES)) for k in range(self.center.numel()) if float(self.weights[b, k, 0]) != 0.0]
        return terms, float(self.bias[0])

    def numpy_kernel(self):
        """The same function in numpy: u [n_in] -> a number, or u [R, n_in] -> [R]."""
        select = self.select.numpy().copy()
        center = self.center.numpy().copy()
        weights = self.weights[:, :, 0].numpy().copy()
        bias = float(self.bias[0])

        def evaluate(u: np.ndarray):
            w = u @ select - center
            magnitude = np.abs(w)
            return bias + w @ weights[0] + magnitude @ weights[1] + (w * magnitude) @ weights[2] + (w * w) @ weights[3]
        return evaluate
