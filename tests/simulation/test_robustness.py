"""FMUs from other tools: a model without continuous states that rejects the state calls with
nx = 0, and a String output (the Reference FMUs' Feedthrough)."""
from pathlib import Path

import fmpy
import numpy as np
import pytest

from fmubuilder.build import build_cmake_project
from fmubuilder.simulation import simulate
from tests.reference_fmus import reference_fmu
from tests.test_cli_errors import run_cli

HERE = Path(__file__).resolve().parent


@pytest.fixture(scope="module")
def stateless_fmu(tmp_path_factory):
    build = build_cmake_project(HERE / "stateless", tmp_path_factory.mktemp("stateless_build"))
    return build.build_dir / "fmus" / "stateless.fmu"


def test_a_model_without_states_that_rejects_nx_0(stateless_fmu):
    result = simulate(stateless_fmu, stop_time=5.0, output_interval=0.25)
    reference = fmpy.simulate_fmu(str(stateless_fmu), fmi_type="ModelExchange", stop_time=5.0, output_interval=0.25)
    between = np.abs(result.time - np.round(result.time)) > 0.1   # away from the steps at whole seconds
    np.testing.assert_array_equal(result["counter"][between], np.floor(result.time[between]))
    expected = np.interp(result.time[between], reference["time"], reference["level"])
    np.testing.assert_array_equal(result["level"][between], expected)


def test_simulate_without_variables_skips_string_outputs(tmp_path):
    fmu = reference_fmu("Feedthrough")
    out = tmp_path / "out.csv"
    proc = run_cli("simulate", fmu, "-o", out)
    assert proc.returncode == 0, proc.stderr
    header = out.read_text().splitlines()[0].split(",")
    numeric = [v.name for v in fmpy.read_model_description(str(fmu), validate=False).modelVariables
               if v.causality == "output" and v.type != "String"]
    assert header == ["time"] + numeric
    assert "String_output" not in header
