"""The hybrid carries the original as it is: every file of its binaries/<platform>/ folder (a
library the binary loads from beside itself), its documentation/ with the licences, extra/, and
every capability flag that still holds (canNotUseMemoryManagementFunctions)."""
from __future__ import annotations

import subprocess
import zipfile
from pathlib import Path

import fmpy
import numpy as np
import pytest
from fmpy.validation import validate_fmu

from fmubuilder.build import build_cmake_project, example_fmu
from fmubuilder.fmi import Fmu, read_model_info
from fmubuilder.fmi.binding import ffi

from .test_wrapper import make_hybrid

HERE = Path(__file__).resolve().parent
DOCUMENTATION = {"documentation/index.html": "<html><body>with_sibling</body></html>\n",
                 "documentation/licenses/LICENSE.txt": "Test licence of the with_sibling model.\n",
                 "extra/org.example/notes.txt": "vendor data\n"}


@pytest.fixture(scope="module")
def with_sibling(tmp_path_factory) -> Path:
    """The test FMU with libsibling.so beside its binary, documentation/ and extra/."""
    build = build_cmake_project(HERE / "with_sibling", tmp_path_factory.mktemp("with_sibling_build"))
    built, sibling = build.fmus()[0], build.build_dir / "sibling" / "libsibling.so"
    fmu = tmp_path_factory.mktemp("with_sibling") / "with_sibling.fmu"
    with zipfile.ZipFile(built) as source, zipfile.ZipFile(fmu, "w", zipfile.ZIP_DEFLATED) as target:
        for item in source.infolist():
            target.writestr(item, source.read(item))
        target.write(sibling, "binaries/linux64/libsibling.so")
        for name, text in DOCUMENTATION.items():
            target.writestr(name, text)
    return fmu


def test_the_original_needs_its_sibling(with_sibling, tmp_path):
    with zipfile.ZipFile(with_sibling) as archive:
        archive.extractall(tmp_path)
    binary = tmp_path / "binaries" / "linux64" / "with_sibling.so"
    needed = subprocess.run(["ldd", str(binary)], capture_output=True, text=True).stdout
    assert "libsibling.so => " + str(tmp_path / "binaries" / "linux64" / "libsibling.so") in needed
    result = fmpy.simulate_fmu(str(with_sibling), stop_time=1.0, output=["x"])
    assert result["x"][-1] == pytest.approx(np.exp(-0.5), rel=1e-3)


def test_hybrid_carries_the_original_and_instantiates_in_fmpy(with_sibling, tmp_path):
    spec, hybrid = make_hybrid(tmp_path, with_sibling, ["der(x)"], ["x"], seed=3, p_ann=[0.0])
    assert validate_fmu(str(hybrid)) == []
    with zipfile.ZipFile(hybrid) as archive:
        names = set(archive.namelist())
        assert {"resources/with_sibling.so", "resources/libsibling.so"} <= names
        for name, text in DOCUMENTATION.items():
            assert archive.read(name).decode() == text
    # The network switched off: the hybrid is the original, sibling library and all.
    original = fmpy.simulate_fmu(str(with_sibling), stop_time=1.0, output=["x"], solver="Euler", step_size=0.01)
    result = fmpy.simulate_fmu(str(hybrid), stop_time=1.0, output=["x"], solver="Euler", step_size=0.01)
    np.testing.assert_array_equal(result["x"], original["x"])


def instantiate_without_memory_functions(fmu_path: Path):
    """fmi2Instantiate with allocateMemory and freeMemory NULL: the component, and the last message."""
    with Fmu(fmu_path) as fmu:
        instance = fmu.instantiate()
        callbacks = ffi.new("fmi2CallbackFunctions*")
        callbacks.logger = instance._callbacks.logger
        callbacks.componentEnvironment = instance._callbacks.componentEnvironment
        resources = ffi.new("char[]", fmu.archive.resources_uri.encode())
        info = read_model_info(fmu_path)
        component = fmu.lib.fmi2Instantiate(b"bare", 0, info.guid.encode(), resources, callbacks, 0, 0)
        found = component != ffi.NULL
        if found:
            fmu.lib.fmi2FreeInstance(component)
        message = instance.messages[-1] if instance.messages else ""
        instance.free()
    return found, message


def test_memory_management_flag_is_kept_and_honoured(with_sibling, tmp_path):
    _, hybrid = make_hybrid(tmp_path / "sibling", with_sibling, ["der(x)"], ["x"], seed=3)
    assert fmpy.read_model_description(str(hybrid)).modelExchange.canNotUseMemoryManagementFunctions
    assert instantiate_without_memory_functions(hybrid)[0]
    # A hybrid of an original without the flag needs the importer's memory functions.
    _, ball = make_hybrid(tmp_path / "ball", example_fmu("bouncing_ball"), ["der(v)"], ["v"], seed=3)
    assert not fmpy.read_model_description(str(ball)).modelExchange.canNotUseMemoryManagementFunctions
    found, message = instantiate_without_memory_functions(ball)
    assert not found and "allocateMemory and freeMemory are required" in message


def test_round_trip_from_the_embedded_spec_finds_the_sibling(with_sibling, tmp_path):
    """`fmubuilder validate HYBRID.fmu` (no --against) rebuilds the original from the hybrid:
    with its sibling library, or the original's binary cannot load."""
    from fmubuilder.export import validate_hybrid
    _, hybrid = make_hybrid(tmp_path, with_sibling, ["der(x)"], ["x"], seed=3)
    report = validate_hybrid(hybrid, stop_time=0.5)
    assert report.passed, report.format_table()
    assert any(not c.informational for c in report.comparisons)
