"""The hybrid FMU for Windows: an original with linux64 and win64 binaries gives a hybrid with
both; its win64 wrapper DLL, run under wine by a C host cross-compiled with mingw-w64, follows
the same trajectory as the linux64 one run by the same host compiled for Linux. Without mingw-w64
or wine these tests skip with the reason."""
from __future__ import annotations

import shutil
import subprocess
import zipfile
from pathlib import Path

import fmpy
import numpy as np
import pytest
from fmpy.validation import validate_fmu

from fmubuilder.build import example_fmu
from fmubuilder.errors import FmuBuilderError
from fmubuilder.export import HybridSpec, export_hybrid
from fmubuilder.export.wrapper import platform_note
from fmubuilder.fmi import read_model_info
from tests.export.test_wrapper import make_hybrid, make_network
from tests.export.win64_fmus import (FMI_HEADERS, HERE, MINGW_COMPILER, MINGW_STATIC, build_hosts, example_with_win64,
                                     host_process, reference_with_win64, relative_difference, require_mingw,
                                     require_wine, run_host, sibling_with_win64, unpacked, value_reference)
from tests.reference_fmus import reference_fmu

# Same source, same IEEE operations (-ffp-contract=off on both): only the C libraries' math
# functions (tanh, exp) may round differently, by an ulp or so.
PLATFORM_TOLERANCE = 1e-12
WINDOWS_SYSTEM_DLLS = {"kernel32.dll", "msvcrt.dll", "ucrtbase.dll"}


@pytest.fixture(scope="module")
def hosts(tmp_path_factory):
    return build_hosts(tmp_path_factory.mktemp("hosts"))


@pytest.fixture(scope="module")
def ball(tmp_path_factory):
    """The Reference FMU BouncingBall (state events with a reset), network on der(v)."""
    original = reference_with_win64(reference_fmu("BouncingBall"), tmp_path_factory.mktemp("ball_original"))
    spec, hybrid = make_hybrid(tmp_path_factory.mktemp("ball"), original, ["der(v)"], ["h", "v"], seed=1)
    return {"spec": spec, "fmu": hybrid, "stop": 3.0, "step": 1e-3, "outputs": ["der(v)"]}


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """The DC drive example (time events; `power` is an alias of the channel der(energy))."""
    original = example_with_win64("dc_drive", tmp_path_factory.mktemp("drive_original"))
    spec, hybrid = make_hybrid(tmp_path_factory.mktemp("drive"), original, ["der(energy)"],
                               ["temperature", "speed"], seed=6, p_ann=[40.0], aliases={"power": "der(energy)"})
    return {"spec": spec, "fmu": hybrid, "stop": 10.0, "step": 1e-3, "outputs": ["der(energy)", "power"]}


@pytest.fixture(scope="module")
def sibling(tmp_path_factory):
    """An original whose DLL imports another DLL from its own folder (LoadLibraryEx must find it)."""
    original = sibling_with_win64(tmp_path_factory.mktemp("sibling_original"))
    spec, hybrid = make_hybrid(tmp_path_factory.mktemp("sibling"), original, ["der(x)"], ["x"], seed=3)
    return {"spec": spec, "fmu": hybrid, "stop": 2.0, "step": 1e-3, "outputs": ["der(x)"]}


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """The DC drive with its inertia calibrated: a hybrid of an override, without channels."""
    original = example_with_win64("dc_drive", tmp_path_factory.mktemp("calibrated_original"))
    spec = HybridSpec.calibration(original, {"inertia": 0.012})
    hybrid = export_hybrid(spec, tmp_path_factory.mktemp("calibrated") / "dc_drive_calibrated.fmu")
    return {"spec": spec, "fmu": hybrid, "stop": 10.0, "step": 1e-3, "outputs": ["speed"]}


def run(case: dict, host: Path, fmu: Path, folder: Path, wine: str | None = None, rewind: bool = False) -> np.ndarray:
    value_references = [value_reference(fmu, name) for name in case["outputs"]]
    return run_host(host, unpacked(fmu, folder), fmu, case["stop"], case["step"], value_references, wine=wine,
                    rewind=rewind)


@pytest.mark.parametrize("name", ["ball", "drive", "sibling", "calibrated"])
def test_hybrid_carries_linux64_and_win64(name, request):
    case = request.getfixturevalue(name)
    hybrid, original = case["fmu"], read_model_info(case["spec"].original_fmu)
    identifier = read_model_info(hybrid).model_identifier
    with zipfile.ZipFile(hybrid) as archive:
        names = set(archive.namelist())
        description = archive.read("modelDescription.xml").decode()
    assert {f"binaries/linux64/{identifier}.so", f"binaries/win64/{identifier}.dll",
            f"binaries/win64/{original.model_identifier}.dll", f"resources/{original.model_identifier}.so"} <= names
    assert {"linux64", "win64"} <= set(fmpy.supported_platforms(str(hybrid)))
    assert "SourceFiles" not in description  # the sources wrap the binaries; they build nowhere alone
    assert validate_fmu(str(hybrid)) == []
    assert platform_note(case["spec"].original_fmu, hybrid) == "binaries: linux64, win64"
    with zipfile.ZipFile(case["spec"].original_fmu) as archive:  # every win64 file of the original
        assert {n for n in archive.namelist() if n.startswith("binaries/win64/") and not n.endswith("/")} < names


def test_static_wrapper_cross_compiles_without_warnings(tmp_path):
    """The wrapper on its own, with the sample configuration: strict C99, every warning an error."""
    require_mingw()
    command = [MINGW_COMPILER, "-std=c99", "-O1", "-shared", "-ffp-contract=off", "-Wall", "-Wextra",
               "-Wno-type-limits", "-Werror", f"-I{HERE / 'host' / 'sample_config'}",
               f"-I{HERE.parents[1] / 'c_templates'}", f"-I{FMI_HEADERS}",
               str(HERE.parents[1] / "c_templates" / "hybrid_wrapper.c"), "-o", str(tmp_path / "sample.dll"),
               *MINGW_STATIC]
    result = subprocess.run(command, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


def test_win64_wrapper_needs_only_windows_dlls_and_exports_fmi2(ball, tmp_path):
    objdump = shutil.which("x86_64-w64-mingw32-objdump")
    if objdump is None:
        pytest.skip("x86_64-w64-mingw32-objdump not found (comes with mingw-w64's binutils)")
    identifier = read_model_info(ball["fmu"]).model_identifier
    dll = unpacked(ball["fmu"], tmp_path) / "binaries" / "win64" / f"{identifier}.dll"
    headers = subprocess.run([objdump, "-p", str(dll)], capture_output=True, text=True, check=True).stdout
    imports = {line.split(":", 1)[1].strip().lower() for line in headers.splitlines() if "DLL Name:" in line}
    assert imports and imports <= WINDOWS_SYSTEM_DLLS, imports
    for function in ("fmi2Instantiate", "fmi2GetDerivatives", "fmi2SerializeFMUstate", "fmi2GetVersion"):
        assert f" {function}\n" in headers


@pytest.mark.parametrize("name", ["ball", "drive", "sibling", "calibrated"])
def test_win64_under_wine_follows_the_linux64_trajectory(name, request, hosts, tmp_path):
    wine = require_wine()
    case = request.getfixturevalue(name)
    linux_host, windows_host = hosts
    linux = run(case, linux_host, case["fmu"], tmp_path / "linux")
    windows = run(case, windows_host, case["fmu"], tmp_path / "windows", wine=wine)
    difference = relative_difference(windows, linux)
    print(f"{name}: {len(linux)} rows, max relative difference win64 (wine) vs linux64 {difference:.3g}")
    assert difference <= PLATFORM_TOLERANCE
    # Not a comparison of two idle runs: the states move, and the network changes them (the
    # original run by the same host follows another trajectory).
    assert np.ptp(linux[:, 1], axis=0) > 0.01
    n_states = len(read_model_info(case["fmu"]).derivatives)
    original = run({**case, "outputs": []}, linux_host, case["spec"].original_fmu, tmp_path / "original")
    assert relative_difference(original, linux[:, :1 + n_states]) > 1e-6


@pytest.mark.parametrize("name", ["ball", "drive"])
def test_win64_fmu_state_rewind_under_wine(name, request, hosts, tmp_path):
    """FMU state taken (and serialized) at the middle, set after the end: the second half again,
    the same on both platforms."""
    wine = require_wine()
    case = request.getfixturevalue(name)
    linux = run(case, hosts[0], case["fmu"], tmp_path / "linux", rewind=True)
    windows = run(case, hosts[1], case["fmu"], tmp_path / "windows", wine=wine, rewind=True)
    steps = round(case["stop"] / case["step"])
    first_pass, replay = linux[:steps + 1], linux[steps + 1:]
    assert len(replay) == steps - steps // 2
    np.testing.assert_array_equal(replay, first_pass[steps // 2 + 1:])
    assert relative_difference(windows, linux) <= PLATFORM_TOLERANCE


def test_win64_wrapper_without_the_original_dll_fails_with_a_message(ball, hosts, tmp_path):
    wine = require_wine()
    fmu_dir = unpacked(ball["fmu"], tmp_path)
    (fmu_dir / "binaries" / "win64" / "BouncingBall.dll").unlink()
    result = host_process(hosts[1], fmu_dir, ball["fmu"], ball["stop"], ball["step"], [], wine=wine)
    assert result.returncode != 0
    # 126: ERROR_MOD_NOT_FOUND
    assert "fmi2Instantiate: cannot load the original FMU's binary BouncingBall.dll (Windows error 126)." \
        in result.stderr


def test_ball_bounces_in_the_compared_run(ball, hosts, tmp_path):
    """The compared span holds state events (the ball's velocity is reset upwards)."""
    linux = run(ball, hosts[0], ball["fmu"], tmp_path)
    velocity = linux[:, 2]
    assert np.count_nonzero(np.diff(velocity) > 0.1) >= 2


def test_win64_required_but_the_original_has_none(tmp_path):
    original = example_fmu("bouncing_ball")
    network = make_network(tmp_path / "network.onnx", 1, 1, seed=0)
    spec = HybridSpec(original_fmu=original, original_guid=read_model_info(original).guid, channels=["der(v)"],
                      inputs=["h"], onnx=network)
    with pytest.raises(FmuBuilderError, match="no binaries/win64/bouncing_ball.dll"):
        export_hybrid(spec, tmp_path / "hybrid.fmu", win64=True)
    assert not (tmp_path / "hybrid.fmu").exists()


def test_without_mingw_the_hybrid_is_linux64_and_says_what_is_missing(ball, tmp_path, monkeypatch):
    real_which = shutil.which
    monkeypatch.setattr(shutil, "which", lambda name, *args, **kwargs:
                        None if "mingw" in name else real_which(name, *args, **kwargs))
    with pytest.raises(FmuBuilderError, match="cannot build the win64 binaries: x86_64-w64-mingw32-gcc not found"):
        export_hybrid(ball["spec"], tmp_path / "required.fmu", win64=True)
    hybrid = export_hybrid(ball["spec"], tmp_path / "hybrid.fmu")
    # fmpy also lists "c-code" for any .c file in sources/, declared or not.
    assert set(fmpy.supported_platforms(str(hybrid))) - {"c-code"} == {"linux64"}
    assert platform_note(ball["spec"].original_fmu, hybrid) == (
        "binaries: linux64; the original also has win64, but x86_64-w64-mingw32-gcc not found; "
        "install mingw-w64 (Debian: apt-get install gcc-mingw-w64-x86-64)")
