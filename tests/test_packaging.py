"""fmubuilder installs like any other package.

The wheel (built from the source distribution, as `python -m build` does) carries the C
templates, CMake files and example sources; installed into a fresh virtual environment it
builds an example FMU and exports a hybrid from them, without the source checkout. Every
third-party module the package imports is a declared dependency, and a missing cmake is one
clear error line.
"""
import ast
import importlib.metadata
import json
import os
import pathlib
import re
import shutil
import subprocess
import sys
import sysconfig
import textwrap
import zipfile

import numpy as np
import pytest

from fmubuilder import build

REPO = pathlib.Path(__file__).resolve().parents[1]
PACKAGE = REPO / "fmubuilder"
NOT_SHIPPED = shutil.ignore_patterns(".git", "build", "dist", "*.egg-info", "__pycache__", ".pytest_cache",
                                     "fmubuilder-demo", "*.fmu")


def _clean_env(**extra) -> dict[str, str]:
    """The environment of a user's shell: no PYTHONPATH pointing at the checkout."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    env.update(extra)
    return env


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> pathlib.Path:
    """sdist, then the wheel from the sdist, of a copy of the checkout."""
    pytest.importorskip("build", reason="the test extras install `build`: pip install -e '.[test]'")
    work = tmp_path_factory.mktemp("package")
    source = work / "source"
    shutil.copytree(REPO, source, ignore=NOT_SHIPPED)
    dist = work / "dist"
    proc = subprocess.run([sys.executable, "-m", "build", "--no-isolation", "--outdir", str(dist), str(source)],
                          capture_output=True, text=True, env=_clean_env())
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    (wheel_file,) = dist.glob("fmubuilder-*.whl")
    return wheel_file


def _see_the_running_site_packages(python: pathlib.Path) -> None:
    """Where the tests run in a venv, --system-site-packages reaches only the base interpreter's
    site, not this venv's dependencies: a .pth line adds them. Only paths are added, so the .pth
    files there (an editable install of the checkout) stay unread."""
    paths = {sysconfig.get_path("purelib"), sysconfig.get_path("platlib")}
    proc = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
                          capture_output=True, text=True, check=True)
    site = pathlib.Path(proc.stdout.strip())
    (site / "running_environment.pth").write_text("".join(f"{p}\n" for p in sorted(paths)))


@pytest.fixture(scope="module")
def venv_python(wheel, tmp_path_factory) -> pathlib.Path:
    """A fresh venv with the wheel installed; torch, fmpy etc. come from the running environment."""
    venv = tmp_path_factory.mktemp("venv")
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(venv)], check=True)
    python = venv / "bin" / "python"
    _see_the_running_site_packages(python)
    # --ignore-installed: a checkout installed in the system site stays untouched.
    proc = subprocess.run([str(python), "-m", "pip", "install", "--no-deps", "--no-index", "--ignore-installed",
                           str(wheel)], capture_output=True, text=True, env=_clean_env())
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return python


def _shipped_files(root: pathlib.Path) -> set[str]:
    files = set()
    for item in build.DATA_ITEMS:
        path = root / item
        candidates = path.rglob("*") if path.is_dir() else [path]
        for candidate in candidates:
            relative = candidate.relative_to(root)
            if candidate.is_file() and not any(p.startswith(".") or p == "__pycache__" for p in relative.parts):
                files.add(relative.as_posix())
    return files


def test_the_wheel_carries_every_template_cmake_file_and_example_source(wheel):
    with zipfile.ZipFile(wheel) as zf:
        prefix = "fmubuilder/_data/"
        packed = {name.removeprefix(prefix) for name in zf.namelist() if name.startswith(prefix)}
        modules = {name for name in zf.namelist() if name.endswith(".py")}
    assert packed == _shipped_files(REPO)
    expected_modules = {p.relative_to(REPO).as_posix() for p in PACKAGE.rglob("*.py")}
    assert expected_modules <= modules, sorted(expected_modules - modules)
    core = {f"fmubuilder/simulation/core/{name}" for name in ("event_loop.c", "event_loop.h", "CMakeLists.txt")}
    with zipfile.ZipFile(wheel) as zf:
        assert core <= set(zf.namelist()), "the compiled simulation core's sources are missing"


# Runs in the venv from a folder outside the checkout: build an example from the installed
# package data, export a fitted-term hybrid, simulate it with fmpy, validate it.
EXPORT_SCRIPT = textwrap.dedent("""
    import json, pathlib, sys
    import fmpy, numpy as np
    from fmpy.validation import validate_fmu
    import fmubuilder
    from fmubuilder.build import example_fmu, repo_root
    from fmubuilder.export import export_hybrid
    from fmubuilder.fmi import read_model_info
    from fmubuilder.hybridize.terms import spec_from_fitted_term
    from fmubuilder.simulation import simulate

    out = pathlib.Path(sys.argv[1])
    fmu = example_fmu("bouncing_ball")
    fitted = {"channel": "der(v)", "terms": [{"variable": "v", "basis": "w", "center": 0.0, "coefficient": -0.4}]}
    spec = spec_from_fitted_term(fitted, fmu, read_model_info(fmu).guid, out)
    hybrid = export_hybrid(spec, out / "hybrid.fmu")
    result = fmpy.simulate_fmu(str(hybrid), stop_time=0.4, output_interval=0.1, output=["h", "v"],
                               relative_tolerance=1e-10)
    falling = simulate(fmu, solver="rk4", step_size=0.01, stop_time=0.4, output_interval=0.1, variables=["v"])
    print(json.dumps({"package": fmubuilder.__file__, "data": str(repo_root()), "example": str(fmu),
                      "core_v": falling["v"].tolist(),
                      "problems": validate_fmu(str(hybrid)),
                      "time": result["time"].tolist(), "v": result["v"].tolist()}))
""")


def test_the_installed_wheel_builds_an_example_and_exports_a_hybrid(venv_python, tmp_path):
    work = tmp_path / "elsewhere"
    work.mkdir()
    (work / "export_check.py").write_text(EXPORT_SCRIPT)
    proc = subprocess.run([str(venv_python), "export_check.py", str(work)], cwd=work, capture_output=True, text=True,
                          env=_clean_env(FMUBUILDER_CACHE=str(tmp_path / "cache")), timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    venv = venv_python.parent.parent
    assert pathlib.Path(report["package"]).is_relative_to(venv), report["package"]
    assert pathlib.Path(report["data"]).is_relative_to(venv), report["data"]
    assert pathlib.Path(report["example"]).is_relative_to(tmp_path / "cache")
    assert report["problems"] == []
    # Before the first impact the corrected model is v' = -g - 0.4 v, v(0) = 0 (analytic).
    g, k = 9.81, 0.4
    t = np.array(report["time"])
    np.testing.assert_allclose(report["v"], -g / k * (1 - np.exp(-k * t)), rtol=1e-6, atol=1e-8)
    # The compiled core, built from the installed sources: RK4 is exact on the free fall v = -g t.
    np.testing.assert_allclose(report["core_v"], -g * t, rtol=1e-12, atol=1e-12)
    assert list((tmp_path / "cache" / "event_loop").glob("*/event_loop.so")), "the core was not built"


def test_the_installed_command_runs(venv_python, tmp_path, bouncing_ball_fmu):
    command = venv_python.parent / "fmubuilder"
    proc = subprocess.run([str(command), "inspect", str(bouncing_ball_fmu)], cwd=tmp_path, capture_output=True,
                          text=True, env=_clean_env(), timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "model identifier                bouncing_ball" in proc.stdout


# ---------------------------------------------------------------------------------------
# Declared dependencies


def _third_party_imports() -> set[str]:
    """Top-level names of every module imported anywhere in the package (also inside functions)."""
    names = set()
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names.update(alias.name.split(".")[0] for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
    return names - set(sys.stdlib_module_names) - {"fmubuilder", "__future__"}


def _declared_distributions() -> set[str]:
    text = (REPO / "pyproject.toml").read_text()
    block = re.search(r"^dependencies = \[(.*?)^\]", text, re.S | re.M).group(1)
    requirements = re.findall(r'^\s*"([^"]+)"', block, re.M)
    return {re.split(r"[<>=!~\[; ]", req, maxsplit=1)[0].lower() for req in requirements}


def _feature_extras() -> set[str]:
    """Distributions of the optional features (`pip install fmubuilder[ray]`), the test extra left out:
    a feature's module may import them, behind a one-line error when they are missing."""
    text = (REPO / "pyproject.toml").read_text()
    block = re.search(r"^\[project.optional-dependencies\](.*?)^\[", text, re.S | re.M).group(1)
    extras = re.findall(r"^(\w+) = \[(.*?)\]", block, re.M)
    return {re.split(r"[<>=!~\[; ]", req, maxsplit=1)[0].lower()
            for name, listed in extras if name != "test" for req in re.findall(r'"([^"]+)"', listed)}


def test_every_imported_third_party_module_is_a_declared_dependency():
    providers = importlib.metadata.packages_distributions()
    declared = _declared_distributions() | _feature_extras()
    undeclared = {}
    for module in sorted(_third_party_imports()):
        distributions = {name.lower() for name in providers.get(module, [module])}
        if not distributions & declared:
            undeclared[module] = sorted(distributions)
    assert not undeclared, f"imported but not in pyproject.toml dependencies: {undeclared}"


def test_cmake_is_a_declared_dependency():
    assert "cmake" in _declared_distributions()


# ---------------------------------------------------------------------------------------
# cmake missing


CLI_WITHOUT_CMAKE = textwrap.dedent("""
    import sys
    sys.modules["cmake"] = None  # hide the cmake Python package too
    from fmubuilder.cli import main
    sys.exit(main(sys.argv[1:]))
""")


def test_without_cmake_the_command_line_prints_one_error_line(tmp_path):
    """Building the examples in an empty cache needs cmake: one line, non-zero exit."""
    script = tmp_path / "no_cmake.py"
    script.write_text(CLI_WITHOUT_CMAKE)
    empty_bin = tmp_path / "bin"
    empty_bin.mkdir()
    env = _clean_env(PATH=str(empty_bin), FMUBUILDER_CACHE=str(tmp_path / "cache"), PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, str(script), "demo", "--output", str(tmp_path / "demo")],
                          capture_output=True, text=True, env=env, cwd=tmp_path, timeout=300)
    assert proc.returncode != 0
    assert "Traceback" not in proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "cmake not found" in lines[0], proc.stderr


def test_the_cmake_of_the_python_package_is_found_off_path(tmp_path, monkeypatch):
    """An environment used without activating it has its bin folder off PATH."""
    cmake = pytest.importorskip("cmake")
    monkeypatch.setenv("PATH", str(tmp_path))
    found = build.find_cmake()
    assert found is not None and pathlib.Path(found).parent == pathlib.Path(cmake.CMAKE_BIN_DIR)
    version = subprocess.run([found, "--version"], capture_output=True, text=True, check=True).stdout
    assert version.startswith("cmake version")
