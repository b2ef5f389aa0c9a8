"""Trained NeuralFMUs and fitted terms become hybrid FMUs that reproduce them.

References: the NeuralFMU's own numpy system (fmubuilder.neural.system) simulated by the engine,
and a numpy evaluation of the fitted expression.
"""
import subprocess
import sys

import numpy as np
import onnxruntime
import pytest
import torch

from fmubuilder.build import example_fmu
from fmubuilder.errors import FmuBuilderError
from fmubuilder.hybridize.terms import FittedTerm, spec_from_fitted_term
from fmubuilder.neural import NeuralFMU, TopologyConfig, save_neural_fmu
from fmubuilder.neural.system import simulate_hybrid
from fmubuilder.simulation import simulate

TERMS = [
    {"variable": "v", "basis": "w", "center": 0.5, "coefficient": -0.3},
    {"variable": "v", "basis": "w*|w|", "center": 0.0, "coefficient": 0.05},
    {"variable": "h", "basis": "|w|", "center": 0.2, "coefficient": 0.7},
    {"variable": "h", "basis": "w^2", "center": 0.0, "coefficient": -0.1},
    {"variable": "time", "basis": "1", "center": 0.0, "coefficient": 0.25},
]


def fitted_reference(h, v):
    return (-0.3 * (v - 0.5) + 0.05 * v * abs(v) + 0.7 * abs(h - 0.2) - 0.1 * h * h + 0.25)


def test_fitted_term_network_matches_the_expression(tmp_path):
    from fmubuilder.export import freeze
    network = FittedTerm(TERMS, ["v", "h"])
    freeze(network.eval(), 2, tmp_path / "term.onnx")
    session = onnxruntime.InferenceSession(str(tmp_path / "term.onnx"))
    name = session.get_inputs()[0].name
    for v, h in np.random.default_rng(0).uniform(-3, 3, size=(50, 2)):
        out = session.run(None, {name: np.array([[v, h]])})[0]
        assert out.item() == pytest.approx(fitted_reference(h, v), rel=1e-13, abs=1e-13)


def test_fitted_term_hybrid_simulates_the_corrected_model(tmp_path):
    from fmubuilder.export import export_hybrid
    fmu = example_fmu("bouncing_ball")
    fitted = {"channel": "der(v)", "terms": [{"variable": "v", "basis": "w", "center": 0.0, "coefficient": -0.4}]}
    from fmubuilder.fmi import read_model_info
    spec = spec_from_fitted_term(fitted, fmu, read_model_info(fmu).guid, tmp_path)
    hybrid = export_hybrid(spec, tmp_path / "hybrid.fmu")
    result = simulate(hybrid, stop_time=0.4, variables=["h", "v"], rtol=1e-10, output_interval=0.1)
    # Before the first impact: v' = -g - 0.4 v, v(0) = 0, h(0) = 1 (analytic).
    g, k, t = 9.81, 0.4, result.time
    v = -g / k * (1 - np.exp(-k * t))
    h = 1 - g / k * t + g / k ** 2 * (1 - np.exp(-k * t))
    np.testing.assert_allclose(result["v"], v, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(result["h"], h, rtol=1e-7, atol=1e-9)


def test_a_time_term_is_not_offered_for_export(tmp_path):
    fitted = {"channel": "der(v)", "terms": [{"variable": "time", "basis": "w", "center": 0.0, "coefficient": 1.0}]}
    assert spec_from_fitted_term(fitted, example_fmu("bouncing_ball"), "{guid}", tmp_path) is None


BASE_TERMS = [{"variable": "v", "basis": "w*|w|", "center": 0.0, "coefficient": -0.02},
              {"variable": "h", "basis": "w", "center": 0.5, "coefficient": 0.3}]


@pytest.fixture(params=["ann", "term + ann"])
def trained_file(tmp_path, request):
    """A NeuralFMU with a random ANN switched on (alone, or added to a fitted term), saved as
    `fmubuilder train` saves it."""
    torch.manual_seed(3)
    base_terms = BASE_TERMS if request.param == "term + ann" else []
    config = TopologyConfig(channels=["der(v)"], inputs=["h", "v"], hidden=[8], kind="residual", base_terms=base_terms)
    model = NeuralFMU(example_fmu("bouncing_ball"), config)
    with torch.no_grad():
        for parameter in model.topology.ann.parameters():
            parameter.normal_(0.0, 0.5)
    path = save_neural_fmu(model, tmp_path / "ball.neuralfmu")
    yield model, path
    model.close()


def test_cli_exports_a_trained_neural_fmu_that_reproduces_it(trained_file, tmp_path):
    model, path = trained_file
    output = tmp_path / "ball_hybrid.fmu"
    proc = subprocess.run([sys.executable, "-m", "fmubuilder.cli", "export", str(path), "-o", str(output)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    names = ["h", "v"]
    exported = simulate(output, stop_time=1.5, variables=names, solver="euler", step_size=1e-3, output_interval=0.05)
    reference = simulate_hybrid(model, start_time=0.0, stop_time=1.5, variables=names, solver="euler",
                                step_size=1e-3, output_interval=0.05)
    plain = simulate(example_fmu("bouncing_ball"), stop_time=1.5, variables=names, solver="euler",
                     step_size=1e-3, output_interval=0.05)
    assert np.max(np.abs(plain["h"] - reference["h"])) > 1e-3   # the ANN changes the motion
    for name in names:
        np.testing.assert_allclose(exported[name], reference[name], rtol=1e-9, atol=1e-11)


def test_cli_export_rejects_a_file_that_is_neither_spec_nor_trained_model(tmp_path):
    bogus = tmp_path / "model.pt"
    bogus.write_bytes(b"\x80\x04 not a model")
    proc = subprocess.run([sys.executable, "-m", "fmubuilder.cli", "export", str(bogus), "-o", str(tmp_path / "x.fmu")],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert proc.stderr.startswith("error: ") and "not a trained NeuralFMU" in proc.stderr
    assert not (tmp_path / "x.fmu").exists()


def test_trained_fmu_parameters_are_refused_for_export(tmp_path):
    from fmubuilder.hybridize.terms import spec_from_neural
    config = TopologyConfig(channels=["der(v)"], inputs=["v"], hidden=[4], parameters=["e"])
    with NeuralFMU(example_fmu("bouncing_ball"), config) as model:
        with pytest.raises(FmuBuilderError, match="trained FMU parameters"):
            spec_from_neural(model, tmp_path)
