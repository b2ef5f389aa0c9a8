"""Effects drawn at random, each evaluated two independent ways: with numpy (the reference the
bench checks against) and as a small ONNX graph (what the truth FMU's channel computes).

An effect enters one state derivative (its channel) as a sum of parts. Each part is one family
applied to variables scaled as z = (v - center) / width, times an amplitude:

    bump        A * sech(z)^2                       a smooth bump (Gaussian-like), peak A at v = center
    stribeck    A * tanh(k z) * sech(z)^2           a sign that fades out away from the center (k > 1)
    sign        A * tanh(k z)                       Coulomb-like: a sign smoothed with sharpness k
    saturation  A * clip(z, -1, 1)                  linear near the center, constant beyond width
    deadzone    A * (relu(z - 1) - relu(-z - 1))    zero within width of the center, linear beyond
    product     A * z1 * z2                         two variables together

sech^2 = 1 - tanh^2 stands in for a Gaussian: the exported kernels hold no Exp (export/kernel.py).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

FAMILIES = ("bump", "stribeck", "sign", "saturation", "deadzone", "product")


@dataclass
class Part:
    family: str
    variables: list[str]        # one, two for a product
    centers: list[float]
    widths: list[float]
    amplitude: float = 1.0
    sharpness: float = 1.0      # k of sign and stribeck

    def shape(self, values: dict[str, np.ndarray]) -> np.ndarray:
        """The part without its amplitude, with numpy."""
        z = [(np.asarray(values[v], float) - c) / w for v, c, w in zip(self.variables, self.centers, self.widths)]
        sech2 = lambda x: 1.0 - np.tanh(x) ** 2
        if self.family == "bump":
            return sech2(z[0])
        if self.family == "stribeck":
            return np.tanh(self.sharpness * z[0]) * sech2(z[0])
        if self.family == "sign":
            return np.tanh(self.sharpness * z[0])
        if self.family == "saturation":
            return np.clip(z[0], -1.0, 1.0)
        if self.family == "deadzone":
            return np.maximum(z[0] - 1.0, 0.0) - np.maximum(-z[0] - 1.0, 0.0)
        if self.family == "product":
            return z[0] * z[1]
        raise ValueError(f"unknown effect family {self.family!r}")

    def describe(self) -> str:
        scaled = [f"({v}-{c:.3g})/{w:.3g}" for v, c, w in zip(self.variables, self.centers, self.widths)]
        sharp = f", k={self.sharpness:.3g}" if self.family in ("sign", "stribeck") else ""
        return f"{self.amplitude:.3g}*{self.family}({', '.join(scaled)}{sharp})"


@dataclass
class Effect:
    channel: str                            # the derivative it enters, "der(x)"
    parts: list[Part] = field(default_factory=list)

    @property
    def inputs(self) -> list[str]:
        """The FMU variables it reads, in a fixed order (the ONNX input's columns)."""
        return sorted({v for part in self.parts for v in part.variables})

    @property
    def family(self) -> str:
        return "+".join(part.family for part in self.parts)

    def evaluate(self, values: dict[str, np.ndarray]) -> np.ndarray:
        return sum(part.amplitude * part.shape(values) for part in self.parts)

    def describe(self) -> str:
        return f"{self.channel} += " + " + ".join(part.describe() for part in self.parts)

    def as_dict(self) -> dict:
        return {"channel": self.channel, "family": self.family, "inputs": self.inputs,
                "expression": self.describe(), "parts": [asdict(p) for p in self.parts]}

    def write_onnx(self, path: Path) -> Path:
        return _OnnxWriter(self.inputs).write(self.parts, path)


class _OnnxWriter:
    """Builds the effect's graph node by node: input [1, n] -> output [1, 1], float64."""

    def __init__(self, inputs: list[str]):
        self.inputs = inputs
        self.nodes, self.constants, self.count = [], [], 0

    def write(self, parts: list[Part], path: Path) -> Path:
        import onnx
        from onnx import TensorProto, helper
        terms = [self.op("Mul", self.part(p), self.constant(p.amplitude)) for p in parts]
        total = terms[0]
        for term in terms[1:]:
            total = self.op("Add", total, term)
        self.nodes.append(helper.make_node("Identity", [total], ["output"]))
        graph = helper.make_graph(
            self.nodes, "effect", [helper.make_tensor_value_info("input", TensorProto.DOUBLE, [1, len(self.inputs)])],
            [helper.make_tensor_value_info("output", TensorProto.DOUBLE, [1, 1])], self.constants)
        onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), path)
        return Path(path)

    def name(self) -> str:
        self.count += 1
        return f"t{self.count}"

    def constant(self, value) -> str:
        from onnx import numpy_helper
        name = self.name()
        self.constants.append(numpy_helper.from_array(np.asarray(value, dtype=np.float64).reshape(-1, 1)
                                                      if np.ndim(value) else np.full((1, 1), value, np.float64), name))
        return name

    def op(self, kind: str, *operands: str) -> str:
        from onnx import helper
        out = self.name()
        self.nodes.append(helper.make_node(kind, list(operands), [out]))
        return out

    def scaled(self, variable: str, center: float, width: float) -> str:
        """(v - center) / width as one Gemm on the input row."""
        from onnx import helper, numpy_helper
        weights = np.zeros((len(self.inputs), 1))
        weights[self.inputs.index(variable), 0] = 1.0 / width
        w, b, out = self.name(), self.name(), self.name()
        self.constants += [numpy_helper.from_array(weights, w),
                           numpy_helper.from_array(np.array([-center / width]), b)]
        self.nodes.append(helper.make_node("Gemm", ["input", w, b], [out]))
        return out

    def sech2(self, z: str) -> str:
        t = self.op("Tanh", z)
        return self.op("Sub", self.constant(1.0), self.op("Mul", t, t))

    def part(self, p: Part) -> str:
        z = [self.scaled(v, c, w) for v, c, w in zip(p.variables, p.centers, p.widths)]
        if p.family == "bump":
            return self.sech2(z[0])
        if p.family == "stribeck":
            return self.op("Mul", self.op("Tanh", self.op("Mul", z[0], self.constant(p.sharpness))), self.sech2(z[0]))
        if p.family == "sign":
            return self.op("Tanh", self.op("Mul", z[0], self.constant(p.sharpness)))
        if p.family == "product":
            return self.op("Mul", z[0], z[1])
        one = self.constant(1.0)
        above = self.op("Relu", self.op("Sub", z[0], one))                 # relu(z - 1)
        below = self.op("Relu", self.op("Neg", self.op("Add", z[0], one)))  # relu(-z - 1)
        if p.family == "saturation":
            return self.op("Add", self.op("Sub", z[0], above), below)
        if p.family == "deadzone":
            return self.op("Sub", above, below)
        raise ValueError(f"unknown effect family {p.family!r}")
