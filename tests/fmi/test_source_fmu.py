"""FMUs that ship C sources but no binary for this machine are compiled once and then used like
any other: simulated, and carried into an exported hybrid.

References: the same FMU with the binary its authors built (Modelica Reference FMUs), simulated
by fmpy, and an analytic solution for the hybrid.
"""
import re
import subprocess
import sys
import zipfile

import fmpy
import numpy as np
import pytest

from fmubuilder.errors import FmuBuilderError
from fmubuilder.fmi.sources import runnable_fmu
from fmubuilder.simulation import simulate
from tests.fmi.broken_fmus import rewrite_fmu
from tests.reference_fmus import reference_fmu

NO_BINARIES = ("binaries/",)


@pytest.fixture(autouse=True)
def private_cache(tmp_path_factory, monkeypatch):
    """One compile cache for this module, away from the user's."""
    monkeypatch.setenv("FMUBUILDER_CACHE", str(tmp_path_factory.getbasetemp() / "source_fmu_cache"))


def without_binaries(name: str, tmp_path, **changes):
    return rewrite_fmu(reference_fmu(name), tmp_path / f"{name}.fmu", drop=NO_BINARIES, **changes)


def fmpy_run(fmu, stop_time):
    return fmpy.simulate_fmu(str(fmu), fmi_type="ModelExchange", solver="CVode", relative_tolerance=1e-9,
                             stop_time=stop_time, output_interval=stop_time / 100)


@pytest.mark.parametrize("name, stop_time", [("VanDerPol", 5.0), ("BouncingBall", 2.0), ("Resource", 1.0)])
def test_a_reference_fmu_without_binaries_runs_on_its_compiled_sources(name, stop_time, tmp_path):
    original = reference_fmu(name)
    source_only = without_binaries(name, tmp_path)
    compiled = runnable_fmu(source_only)
    assert compiled != source_only and runnable_fmu(source_only) == compiled  # cached
    assert runnable_fmu(original) == original  # an FMU with a binary is used as it is
    assert fmpy.validation.validate_fmu(str(compiled)) == []

    theirs = fmpy_run(original, stop_time)  # the binary the FMU's authors built
    ours = fmpy_run(compiled, stop_time)
    for column in theirs.dtype.names:
        np.testing.assert_allclose(ours[column], theirs[column], rtol=1e-10, atol=1e-12, err_msg=column)

    # The engine opens the source-only file itself and gets the same trajectory as from the original.
    from_sources = simulate(source_only, stop_time=stop_time, rtol=1e-9, atol=1e-10)
    from_binary = simulate(original, stop_time=stop_time, rtol=1e-9, atol=1e-10)
    for column in from_binary.names:
        np.testing.assert_allclose(from_sources[column], from_binary[column], rtol=1e-12, atol=1e-14)


BUILD_DESCRIPTION = """<?xml version="1.0" encoding="UTF-8"?>
<fmiBuildDescription fmiVersion="3.0">
  <BuildConfiguration modelIdentifier="VanDerPol">
    <SourceFileSet language="C99">
      <SourceFile name="fmi2Functions.c"/>
      <SourceFile name="model.c"/>
      <SourceFile name="cosimulation.c"/>
      {definition}
    </SourceFileSet>
  </BuildConfiguration>
</fmiBuildDescription>
"""


def with_build_description(tmp_path, definition: str):
    """VanDerPol with sources/buildDescription.xml instead of <SourceFiles>: three files, and
    FMI_VERSION as a definition (model.h stops with #error without it)."""
    drop_source_files = lambda xml: re.sub(r"\s*<SourceFiles>.*?</SourceFiles>", "", xml, flags=re.S)
    path = without_binaries("VanDerPol", tmp_path, xml=drop_source_files)
    with zipfile.ZipFile(path, "a") as zf:
        zf.writestr("sources/buildDescription.xml", BUILD_DESCRIPTION.format(definition=definition))
    return path


def test_a_build_description_gives_the_files_and_definitions(tmp_path):
    path = with_build_description(tmp_path, '<PreprocessorDefinition name="FMI_VERSION" value="2"/>')
    theirs = fmpy_run(reference_fmu("VanDerPol"), 3.0)
    ours = fmpy_run(runnable_fmu(path), 3.0)
    np.testing.assert_allclose(ours["x0"], theirs["x0"], rtol=1e-10, atol=1e-12)


def test_sources_that_do_not_compile_name_the_first_compiler_error(tmp_path):
    path = with_build_description(tmp_path, "")  # FMI_VERSION missing
    with pytest.raises(FmuBuilderError) as caught:
        runnable_fmu(path)
    message = str(caught.value)
    assert "\n" not in message
    assert "compiling its sources failed" in message
    # The file as the FMU names it, not the scratch folder (files compile in parallel: either #error).
    assert re.search(r": sources/\w+\.[ch]:\d+:\d+: error: #error FMI_VERSION must be", message), message


def run_cli(*args, env_cache):
    import os
    env = {**os.environ, "FMUBUILDER_CACHE": str(env_cache)}
    return subprocess.run([sys.executable, "-m", "fmubuilder.cli", *map(str, args)], capture_output=True, text=True,
                          env=env, timeout=300)


def test_the_command_line_says_once_which_binary_it_uses(tmp_path):
    path = without_binaries("Dahlquist", tmp_path)
    proc = run_cli("simulate", path, "--output", tmp_path / "out.csv", env_cache=tmp_path / "cache")
    assert proc.returncode == 0, proc.stderr
    notes = [line for line in proc.stderr.splitlines() if "compiled from its sources" in line]
    assert len(notes) == 1 and str(path) in notes[0]


def test_a_broken_source_is_one_error_line_on_the_command_line(tmp_path):
    path = without_binaries("Dahlquist", tmp_path)
    broken = tmp_path / "broken.fmu"
    with zipfile.ZipFile(path) as zin, zipfile.ZipFile(broken, "w") as zout:
        for item in zin.infolist():
            data = zin.read(item)
            if item.filename == "sources/model.c":
                data += b"\nint broken_line(void) { return no_such_name; }\n"
            zout.writestr(item, data)
    proc = run_cli("simulate", broken, env_cache=tmp_path / "cache")
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    assert "sources/model.c" in lines[0] and "no_such_name" in lines[0] and "error:" in lines[0]


def test_a_declared_source_outside_the_sources_folder_is_refused(tmp_path):
    escape = lambda xml: xml.replace('<File name="all.c"/>', '<File name="../../escape.c"/>', 1)
    path = rewrite_fmu(reference_fmu("VanDerPol"), tmp_path / "escape.fmu", drop=NO_BINARIES, xml=escape)
    with zipfile.ZipFile(path, "a") as zf:
        zf.writestr("sources/../../escape.c", "int x;\n")
    with pytest.raises(FmuBuilderError, match="points outside the archive"):
        runnable_fmu(path)


def test_an_exported_hybrid_carries_the_compiled_binary(tmp_path, bouncing_ball_fmu):
    """Our bouncing ball without its binary; a fitted damping term; the hybrid from fmpy against
    the analytic solution before the first impact."""
    from fmubuilder.export import export_hybrid
    from fmubuilder.fmi import read_model_info
    from fmubuilder.hybridize.terms import spec_from_fitted_term

    source_only = rewrite_fmu(bouncing_ball_fmu, tmp_path / "bouncing_ball.fmu", drop=NO_BINARIES)
    fitted = {"channel": "der(v)", "terms": [{"variable": "v", "basis": "w", "center": 0.0, "coefficient": -0.4}]}
    spec = spec_from_fitted_term(fitted, source_only, read_model_info(source_only).guid, tmp_path)
    hybrid = export_hybrid(spec, tmp_path / "hybrid.fmu")
    with zipfile.ZipFile(hybrid) as zf, zipfile.ZipFile(runnable_fmu(source_only)) as compiled:
        assert zf.read("resources/bouncing_ball.so") == compiled.read("binaries/linux64/bouncing_ball.so")
    result = fmpy.simulate_fmu(str(hybrid), stop_time=0.4, output_interval=0.1, output=["v"], relative_tolerance=1e-10)
    g, k, t = 9.81, 0.4, result["time"]
    np.testing.assert_allclose(result["v"], -g / k * (1 - np.exp(-k * t)), rtol=1e-6, atol=1e-8)
