"""Hybrid specs for the two kinds of added effect: a trained NeuralFMU and a fitted symbolic term.

Both become the same thing for export: a network (ONNX) from FMU variables to the correction
of one derivative channel, plus the gates and aliases (see fmubuilder.export.spec).
"""
from __future__ import annotations

from pathlib import Path

from torch import nn

from ..errors import FmuBuilderError
from ..export import freeze
from ..export.spec import HybridSpec
from ..neural.base_term import FittedTerm
from .term_started import fmu_term_inputs


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


def spec_from_fitted_term(fitted: dict, fmu_path: Path, guid: str, folder: Path,
                          aliases: dict[str, str] | None = None) -> HybridSpec | None:
    """The hybrid of a fitted term from the diagnosis (None when it depends on time itself,
    which an FMU cannot take as a variable input)."""
    inputs = fmu_term_inputs(fitted["terms"])
    if not inputs:
        return None
    onnx_path = folder / "term.onnx"
    freeze(FittedTerm(fitted["terms"], inputs).eval(), len(inputs), onnx_path)
    spec = HybridSpec(original_fmu=Path(fmu_path).resolve(), original_guid=guid, channels=[fitted["channel"]],
                      inputs=inputs, onnx=onnx_path, p_ann=[1.0], p_fmu=[1.0], aliases=aliases or {},
                      term="fitted term", expression=fitted.get("expression", ""))
    spec.save(folder / "spec.json")
    return spec
