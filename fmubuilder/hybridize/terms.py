"""Hybrid specs for the two kinds of added effect: a trained NeuralFMU and a fitted symbolic term.

Both become the same thing for export: a network (ONNX) from FMU variables to the correction
of one derivative channel, plus the gates (see fmubuilder.export.spec). `aliases` names the
outputs that equal a channel's derivative ({"power": "der(energy)"}): the hybrid corrects them
with it.
"""
from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from ..errors import FmuBuilderError
from ..export import freeze
from ..export.spec import HybridSpec

DTYPE = torch.float64


class _Correction(nn.Module):
    """The ANN part of a NeuralFMU topology, pre- and post-processing included."""

    def __init__(self, topology):
        super().__init__()
        self.topology = topology

    def forward(self, inputs):
        return self.topology.correction(inputs)


def spec_from_neural(model, folder: Path, aliases: dict[str, str] | None = None) -> HybridSpec:
    """Freeze a trained NeuralFMU's correction network and describe the hybrid it forms."""
    topology = model.topology
    if topology.config.parameters:
        raise FmuBuilderError("exporting trained FMU parameters is not supported; train without --parameters")
    if not topology.has_ann:
        raise FmuBuilderError("the NeuralFMU has no ANN to export; give at least one target derivative")
    onnx_path = folder / "network.onnx"
    freeze(_Correction(topology).eval(), len(topology.config.inputs), onnx_path)
    spec = HybridSpec(original_fmu=model.fmu_path.resolve(), original_guid=model.guid,
                      channels=list(topology.config.channels), inputs=list(topology.config.inputs),
                      onnx=onnx_path, p_ann=topology.gate_ann.detach().tolist(),
                      p_fmu=topology.gate_fmu.detach().tolist(), aliases=aliases or {})
    spec.save(folder / "spec.json")
    return spec


def to_hybrid_spec(trained_path: Path, folder: Path) -> HybridSpec:
    """The spec of a trained NeuralFMU file (`fmubuilder train -o`), for `fmubuilder export`."""
    from ..neural.io import load_neural_fmu
    model = load_neural_fmu(trained_path)
    try:
        return spec_from_neural(model, folder)
    finally:
        model.close()


class FittedTerm(nn.Module):
    """sum_k coefficient_k * basis_k(w_k - center_k) over the terms of a fitted expression,
    written with ops the C kernel supports (MatMul, Sub, Abs, Mul, Add): each term gets its own
    column w_k = u @ select_k, since one variable may appear with different centers."""

    BASES = ("w", "|w|", "w*|w|", "w^2")

    def __init__(self, terms: list[dict], inputs: list[str]):
        super().__init__()
        variable_terms = [t for t in terms if t["basis"] != "1"]
        count = max(len(variable_terms), 1)
        self.register_buffer("select", torch.zeros(len(inputs), count, dtype=DTYPE))
        self.register_buffer("center", torch.zeros(count, dtype=DTYPE))
        self.register_buffer("weights", torch.zeros(len(self.BASES), count, 1, dtype=DTYPE))
        self.register_buffer("bias", torch.tensor([sum(float(t["coefficient"]) for t in terms if t["basis"] == "1")],
                                                  dtype=DTYPE))
        for k, term in enumerate(variable_terms):
            if term["basis"] not in self.BASES:
                raise FmuBuilderError(f"cannot export the term form {term['basis']!r}")
            self.select[inputs.index(term["variable"]), k] = 1.0
            self.center[k] = float(term["center"])
            self.weights[self.BASES.index(term["basis"]), k, 0] = float(term["coefficient"])
        self.used = [b for b in range(len(self.BASES)) if bool(self.weights[b].any())]

    def forward(self, u):
        w = u @ self.select - self.center
        out = self.bias
        for b in self.used:
            phi = (w, torch.abs(w), w * torch.abs(w), w * w)[b]
            out = out + phi @ self.weights[b]
        return out


def spec_from_fitted_term(fitted: dict, fmu_path: Path, guid: str, folder: Path,
                          aliases: dict[str, str] | None = None) -> HybridSpec | None:
    """The hybrid of a fitted term from the diagnosis (None when it depends on time itself,
    which an FMU cannot take as a variable input)."""
    terms = fitted["terms"]
    if any(t["variable"] == "time" for t in terms if t["basis"] != "1"):
        return None
    inputs = list(dict.fromkeys(t["variable"] for t in terms if t["basis"] != "1"))
    if not inputs:
        return None
    onnx_path = folder / "term.onnx"
    freeze(FittedTerm(terms, inputs).eval(), len(inputs), onnx_path)
    spec = HybridSpec(original_fmu=Path(fmu_path).resolve(), original_guid=guid, channels=[fitted["channel"]],
                      inputs=inputs, onnx=onnx_path, p_ann=[1.0], p_fmu=[1.0], aliases=aliases or {},
                      term="fitted term", expression=fitted.get("expression", ""))
    spec.save(folder / "spec.json")
    return spec
