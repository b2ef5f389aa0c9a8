"""The exported modelDescription says what the hybrid contains: a fitted term is named a term
(not a neural network) in the description, the gate and the value variables; the gates are
dimensionless (unit "1", defined); no SourceFiles are declared (the sources only wrap a linux64
binary)."""
from __future__ import annotations

import zipfile

import fmpy
from fmpy.validation import validate_fmu

from fmubuilder.build import example_fmu
from fmubuilder.export import export_hybrid
from fmubuilder.fmi import read_model_info

from .test_wrapper import make_hybrid

FITTED = {"channel": "der(v)", "expression": "-0.4 * v",
          "terms": [{"variable": "v", "basis": "w", "center": 0.0, "coefficient": -0.4}]}


def added_variables(fmu):
    original = read_model_info(example_fmu("bouncing_ball")).variables
    md = fmpy.read_model_description(str(fmu))
    return md, {v.name: v for v in md.modelVariables if v.name not in original}


def check_common(fmu, md, added, gate: str):
    with zipfile.ZipFile(fmu) as archive:
        assert b"SourceFiles" not in archive.read("modelDescription.xml")
    assert "1" in [unit.name for unit in md.unitDefinitions]
    for name in (gate, "hybrid.v.p_fmu"):
        assert added[name].unit == "1" and added[name].variability == "tunable"


def test_a_fitted_term_hybrid_calls_itself_a_fitted_term(tmp_path):
    from fmubuilder.hybridize.terms import spec_from_fitted_term
    fmu = example_fmu("bouncing_ball")
    spec = spec_from_fitted_term(FITTED, fmu, read_model_info(fmu).guid, tmp_path)
    hybrid = export_hybrid(spec, tmp_path / "hybrid.fmu")
    assert validate_fmu(str(hybrid)) == []
    md, added = added_variables(hybrid)
    assert set(added) == {"hybrid.v.p_term", "hybrid.v.p_fmu", "hybrid.v.term"}
    texts = [md.description] + [v.description for v in added.values()]
    assert "fitted term -0.4 * v" in md.description
    assert not any("network" in text or "ANN" in text for text in texts), texts
    check_common(hybrid, md, added, "hybrid.v.p_term")


def test_a_network_hybrid_calls_itself_a_neural_network(tmp_path):
    _, hybrid = make_hybrid(tmp_path, example_fmu("bouncing_ball"), ["der(v)"], ["h", "v"], seed=2)
    md, added = added_variables(hybrid)
    assert set(added) == {"hybrid.v.p_ann", "hybrid.v.p_fmu", "hybrid.v.ann"}
    assert "corrected by the neural network" in md.description
    assert "neural network" in added["hybrid.v.p_ann"].description
    check_common(hybrid, md, added, "hybrid.v.p_ann")
