"""Original FMUs with both linux64 and win64 binaries, for the win64 hybrid tests, and a C host
built for both platforms. The win64 binaries are cross-compiled with mingw-w64 from the same C
sources as the linux64 ones; tests that need mingw-w64 or wine skip visibly without them."""
from __future__ import annotations

import os
import shutil
import subprocess
import zipfile
from pathlib import Path

import fmpy
import numpy as np
import pytest

from fmubuilder.build import build_cmake_project, example_fmu, repo_root
from fmubuilder.export.wrapper import MINGW_COMPILER, MINGW_TOOLCHAIN

HERE = Path(__file__).resolve().parent
FMI_HEADERS = Path(fmpy.__file__).parent / "c-code"
HOST_SOURCE = HERE / "host" / "euler_host.c"
# The compiler's runtime linked in, so nothing but Windows' own DLLs is needed beside a binary.
MINGW_STATIC = ["-static-libgcc", "-static"]


def require_mingw() -> None:
    if shutil.which(MINGW_COMPILER) is None:
        pytest.skip(f"{MINGW_COMPILER} not found: install mingw-w64 (Debian: apt-get install gcc-mingw-w64-x86-64)")


def require_wine() -> str:
    for name in ("wine64", "wine"):
        if shutil.which(name):
            return name
    pytest.skip("wine not found: install it to run win64 binaries (Debian: apt-get install wine64)")


def example_with_win64(name: str, folder: Path) -> Path:
    """The example FMU `name` with binaries/win64/ added from a mingw-w64 build of the same sources."""
    require_mingw()
    build = build_cmake_project(repo_root(), folder / "build-win64", target=name,
                                definitions={"CMAKE_TOOLCHAIN_FILE": MINGW_TOOLCHAIN.as_posix()})
    with zipfile.ZipFile(build.build_dir / "fmus" / f"{name}.fmu") as built:
        win64 = {item: built.read(item) for item in built.namelist() if item.startswith("binaries/win64/")}
    return with_files(example_fmu(name), win64, folder / f"{name}.fmu")


def reference_with_win64(original: Path, folder: Path) -> Path:
    """A Reference FMU (sources/all.c) with binaries/win64/<id>.dll compiled from its sources."""
    require_mingw()
    sources = folder / "sources"
    with zipfile.ZipFile(original) as archive:
        for item in archive.namelist():
            if item.startswith("sources/"):
                archive.extract(item, folder)
    identifier = fmpy.read_model_description(str(original)).modelExchange.modelIdentifier
    dll = folder / f"{identifier}.dll"
    subprocess.run([MINGW_COMPILER, "-shared", "-O2", "-DDISABLE_PREFIX", *MINGW_STATIC, "-I", str(sources),
                    "-I", str(FMI_HEADERS), str(sources / "all.c"), "-o", str(dll)], check=True)
    return with_files(original, {f"binaries/win64/{identifier}.dll": dll.read_bytes()},
                      folder / original.name)


def with_files(fmu: Path, files: dict[str, bytes], output: Path) -> Path:
    """A copy of `fmu` at `output` with `files` (entry name -> content) added."""
    with zipfile.ZipFile(fmu) as source, zipfile.ZipFile(output, "w", zipfile.ZIP_DEFLATED) as target:
        for item in source.infolist():
            target.writestr(item, source.read(item))
        for name, content in files.items():
            target.writestr(name, content)
    return output


def build_hosts(folder: Path) -> tuple[Path, Path]:
    """euler_host for linux64 (cc) and for win64 (mingw-w64)."""
    require_mingw()
    linux, windows = folder / "euler_host", folder / "euler_host.exe"
    common = ["-O2", "-ffp-contract=off", "-I", str(FMI_HEADERS), str(HOST_SOURCE)]
    subprocess.run(["cc", *common, "-o", str(linux), "-ldl", "-lm"], check=True)
    subprocess.run([MINGW_COMPILER, *common, *MINGW_STATIC, "-o", str(windows)], check=True)
    return linux, windows


def unpacked(fmu: Path, folder: Path) -> Path:
    with zipfile.ZipFile(fmu) as archive:
        archive.extractall(folder)
    return folder


def run_host(host: Path, fmu_dir: Path, fmu: Path, stop_time: float, step_size: float,
             value_references: list[int], wine: str | None = None, rewind: bool = False) -> np.ndarray:
    """The host's trajectory (rows: t, states, values) for the unpacked FMU in fmu_dir; with
    `rewind`, the second half follows again from the FMU state taken at the middle."""
    result = host_process(host, fmu_dir, fmu, stop_time, step_size, value_references, wine, rewind)
    assert result.returncode == 0, f"{host.name} failed:\n{result.stderr[-3000:]}"
    return np.loadtxt(result.stdout.splitlines(), ndmin=2)


def host_process(host: Path, fmu_dir: Path, fmu: Path, stop_time: float, step_size: float,
                 value_references: list[int], wine: str | None = None,
                 rewind: bool = False) -> subprocess.CompletedProcess:
    """Runs the host on the unpacked FMU in fmu_dir; under wine the folder is given as a path on
    wine's Z: drive (the Unix root)."""
    description = fmpy.read_model_description(str(fmu))
    folder = f"Z:{fmu_dir}" if wine else str(fmu_dir)
    arguments = ["--rewind"] * rewind + [
        folder, description.modelExchange.modelIdentifier, description.guid, str(len(description.derivatives)),
        str(description.numberOfEventIndicators), repr(stop_time), repr(step_size), *map(str, value_references)]
    command = [wine, str(host), *arguments] if wine else [str(host), *arguments]
    environment = {**os.environ, "WINEDEBUG": "-all"}
    return subprocess.run(command, capture_output=True, text=True, env=environment, timeout=300)


def relative_difference(a: np.ndarray, b: np.ndarray) -> float:
    """max |a - b| / max(|a|, |b|, 1) over all entries (relative for large values, absolute near 0)."""
    assert a.shape == b.shape, f"the trajectories differ in shape: {a.shape} vs {b.shape}"
    scale = np.maximum(np.maximum(np.abs(a), np.abs(b)), 1.0)
    return float(np.max(np.abs(a - b) / scale))


def value_reference(fmu: Path, name: str) -> int:
    for variable in fmpy.read_model_description(str(fmu)).modelVariables:
        if variable.name == name:
            return variable.valueReference
    raise KeyError(name)


def sibling_with_win64(folder: Path) -> Path:
    """tests/export/with_sibling for both platforms: its binary needs a second library beside it
    (libsibling.so, libsibling.dll), as tools ship runtime libraries."""
    require_mingw()
    project = HERE / "with_sibling"
    linux = build_cmake_project(project, folder / "build-linux64")
    windows = build_cmake_project(project, folder / "build-win64",
                                  definitions={"CMAKE_TOOLCHAIN_FILE": MINGW_TOOLCHAIN.as_posix()})
    with zipfile.ZipFile(windows.fmus()[0]) as built:
        files = {item: built.read(item) for item in built.namelist() if item.startswith("binaries/win64/")}
    files["binaries/linux64/libsibling.so"] = (linux.build_dir / "sibling" / "libsibling.so").read_bytes()
    files["binaries/win64/libsibling.dll"] = (windows.build_dir / "libsibling.dll").read_bytes()
    return with_files(linux.fmus()[0], files, folder / "with_sibling.fmu")
