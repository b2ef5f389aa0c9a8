"""A legal Model-Exchange-only FMU whose binary leaves out the Co-Simulation functions (FMI 2.0.5,
p. 69: an FMU implements the functions of the interface types it declares): examples/dc_drive
built with WITHOUT_CO_SIMULATION_SYMBOLS (examples/common/fmi2_glue.c).

Every candidate kind is exported from it and run, and the published hybrid passes fmpy's
validation and simulates in fmpy's CVode. References: fmpy on the original binary (with the
calibrated value as a start value), and the symbol table of the binary itself.
"""
import ctypes
import os
import zipfile

import numpy as np
import pytest
from fmpy import simulate_fmu
from fmpy.validation import validate_fmu

from fmubuilder import synth
from fmubuilder.build import example_fmu
from fmubuilder.export import HybridSpec, export_hybrid
from fmubuilder.hybridize import hybridize
from fmubuilder.hybridize.term_started import NAME as ANN_ON_THE_TERM

MODEL = "dc_drive_model_exchange_only"
BENCH = dict(signals=("speed", "current", "power", "temperature"),
             noise_std={"speed": 0.1, "current": 0.02, "power": 1.0, "temperature": 0.02})
CVODE = dict(fmi_type="ModelExchange", solver="CVode", stop_time=5.0, output=["speed", "current", "temperature"])


def exported(fmu, folder, names) -> set[str]:
    """Which of `names` the FMU's linux64 binary exports, as the dynamic loader finds them."""
    with zipfile.ZipFile(fmu) as archive:
        binary = next(n for n in archive.namelist() if n.startswith("binaries/linux64/") and n.endswith(".so"))
        path = archive.extract(binary, folder)
    library = ctypes.CDLL(path, mode=os.RTLD_LOCAL | os.RTLD_NOW)
    return {name for name in names if hasattr(library, name)}


def test_the_binary_lacks_the_co_simulation_functions(tmp_path):
    model_exchange = {"fmi2GetDerivatives", "fmi2GetFMUstate", "fmi2Instantiate"}
    co_simulation = {"fmi2DoStep", "fmi2SetRealInputDerivatives", "fmi2GetRealOutputDerivatives", "fmi2GetStatus"}
    assert exported(example_fmu(MODEL), tmp_path, model_exchange | co_simulation) == model_exchange


def test_a_calibration_of_it_validates_and_simulates_in_cvode(tmp_path):
    original = example_fmu(MODEL)
    hybrid = export_hybrid(HybridSpec.calibration(original, {"inertia": 0.012}), tmp_path / "calibrated.fmu")
    assert validate_fmu(str(hybrid)) == []
    mine = simulate_fmu(str(hybrid), **CVODE)                                     # no start values
    reference = simulate_fmu(str(original), start_values={"inertia": 0.012}, **CVODE)
    declared = simulate_fmu(str(original), **CVODE)
    for name in CVODE["output"]:
        np.testing.assert_allclose(mine[name], reference[name], rtol=1e-12, atol=1e-12)
    assert np.max(np.abs(declared["speed"] - reference["speed"])) > 0.5          # the value matters


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("model_exchange_only")

    def measure(window, seed):
        settings = synth.BenchSettings(seed=seed, **BENCH)
        measurement = synth.measure(example_fmu("dc_drive_truth_windage"), start_time=window[0],
                                    stop_time=window[1], settings=settings)
        return synth.write_measurement(measurement, folder / f"{seed}.csv")
    return hybridize(example_fmu(MODEL), measure((0.0, 10.0), 0), measure((20.5, 26.0), 1), folder / "hybrid.fmu",
                     folder / "report", budget=1, allow_insignificant=True, progress=False)


def test_hybridize_builds_every_candidate_kind_from_it(run):
    selection = run.report["selection"]
    assert selection["failed"] == {}
    names = [m["name"] for m in run.report["models"]]
    assert {"fitted term", "neural"} <= set(names)
    assert any(name.startswith("calibrated ") for name in names), names
    assert ANN_ON_THE_TERM in names or ANN_ON_THE_TERM in selection["not_trained"], names


def test_the_published_hybrid_validates_and_simulates_in_cvode(run):
    assert run.hybrid_fmu is not None and run.report["roundtrip"]["passed"]
    assert validate_fmu(str(run.hybrid_fmu)) == []
    result = simulate_fmu(str(run.hybrid_fmu), **CVODE)
    assert result["time"][-1] == pytest.approx(CVODE["stop_time"])
    assert all(np.all(np.isfinite(result[name])) for name in CVODE["output"])
