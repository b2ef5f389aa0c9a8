"""Compile C FMU projects with CMake, and find the files those builds need.

* :func:`build_cmake_project` configures and builds any CMake project (the example FMUs,
  source FMUs, the exported hybrid FMUs) and turns a missing tool or a failed build into an
  :class:`~fmubuilder.errors.FmuBuilderError` that shows the tail of the compiler output.
  cmake is the one on PATH, else the one of the `cmake` Python package (a dependency).
* :func:`example_fmu` returns a built example FMU from ``examples/``. All examples are built
  together on first use into a cache directory keyed by a hash of their C sources and CMake
  files, so an unchanged tree reuses the FMUs and an edit triggers a rebuild.
* :func:`repo_root` / :func:`data_path` locate the C templates, CMake files and example
  sources: in the source checkout, or in the copy an installed package carries.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import pathlib
import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass

from fmubuilder.errors import FmuBuilderError

# Bump when the cache layout or the build flags change, to invalidate old caches.
_CACHE_FORMAT = "1"
_LOG_TAIL_LINES = 40
_FAILED_BUILD_LOG = "build.log"


@dataclass(frozen=True)
class CMakeBuild:
    """A finished CMake build: where it is and what the tools printed."""

    build_dir: pathlib.Path
    output: str

    def fmus(self) -> list[pathlib.Path]:
        """The FMUs packed by add_fmu() (cmake/fmu.cmake) in this build."""
        return sorted((self.build_dir / "fmus").glob("*.fmu"))


# ---------------------------------------------------------------------------------------
# Generic CMake build


def build_cmake_project(source_dir: str | os.PathLike, build_dir: str | os.PathLike, target: str | None = None,
                        definitions: dict[str, str] | None = None, keep_going: bool = False,
                        progress_label: str | None = None) -> CMakeBuild:
    """Configure and build ``source_dir`` into ``build_dir`` (Release, all cores).

    ``target`` builds one target instead of all; ``definitions`` become ``-D`` cache
    entries. With ``keep_going`` the build continues past failing targets and reports
    success; the caller then checks which outputs exist.
    """
    source_dir = pathlib.Path(source_dir).resolve()
    build_dir = pathlib.Path(build_dir).resolve()
    if not (source_dir / "CMakeLists.txt").is_file():
        raise FmuBuilderError(f"no CMakeLists.txt in {source_dir}: pass the root of a CMake project")
    cmake = _require_tools()

    cache_entries = {"CMAKE_BUILD_TYPE": "Release"}
    headers = fmi_headers_dir()
    if headers is not None:
        cache_entries["FMI_HEADERS_DIR"] = str(headers)
    cache_entries.update(definitions or {})

    configure = [cmake, "-S", str(source_dir), "-B", str(build_dir)]
    configure += [f"-D{key}={value}" for key, value in cache_entries.items()]
    output = _run(configure, "configuring", source_dir, check=True)

    build = [cmake, "--build", str(build_dir), "--parallel", str(os.cpu_count() or 1)]
    if target is not None:
        build += ["--target", target]
    if keep_going:
        build += ["--", *_keep_going_flags(build_dir)]
    output += _run(build, "building", source_dir, check=not keep_going, progress_label=progress_label)
    return CMakeBuild(build_dir=build_dir, output=output)


def _require_tools() -> str:
    cmake = find_cmake()
    if cmake is None:
        raise FmuBuilderError(
            "cmake not found, neither on PATH nor as the Python package `cmake`: "
            "install it with `pip install cmake` (or apt-get install cmake)")
    c_compiler()    # CMake's own message about a missing compiler is far less clear
    return cmake


def c_compiler() -> str:
    """$CC, else cc, gcc or clang, whichever is on PATH first."""
    compiler = next((c for c in (os.environ.get("CC", ""), "cc", "gcc", "clang") if c and shutil.which(c)), None)
    if compiler is None:
        raise FmuBuilderError("no C compiler found (cc, gcc, clang or $CC): install one, e.g. "
                              "apt-get install build-essential")
    return compiler


def find_cmake() -> str | None:
    """cmake on PATH, else the one of the `cmake` Python package (a declared dependency):
    its launcher sits in the environment's bin folder, which is not on PATH when the
    environment is not activated."""
    on_path = shutil.which("cmake")
    if on_path is not None:
        return on_path
    try:
        import cmake
    except ImportError:
        return None
    return shutil.which("cmake", path=cmake.CMAKE_BIN_DIR)


def fmi_headers_dir() -> pathlib.Path | None:
    """fmpy ships the FMI 2.0 headers; CMake would otherwise ask whatever python is on PATH."""
    try:
        import fmpy
    except ImportError:
        return None
    headers = pathlib.Path(fmpy.__file__).parent / "c-code"
    return headers if (headers / "fmi2Functions.h").is_file() else None


def _keep_going_flags(build_dir: pathlib.Path) -> list[str]:
    cache = (build_dir / "CMakeCache.txt").read_text(errors="replace")
    return ["-k", "0"] if "CMAKE_GENERATOR:INTERNAL=Ninja" in cache else ["-k"]


class CMakeBuildError(FmuBuilderError):
    """A failed configure or build step; ``output`` holds everything the tools printed."""

    def __init__(self, message: str, output: str):
        super().__init__(message)
        self.output = output


def _run(command: list[str], what: str, source_dir: pathlib.Path, check: bool,
         progress_label: str | None = None) -> str:
    if progress_label is None:
        result = subprocess.run(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        code, output = result.returncode, result.stdout
    else:
        code, output = _run_with_progress(command, progress_label)
    if check and code != 0:
        raise CMakeBuildError(f"{what} {source_dir} with CMake failed (exit code {code}); fix the errors below:\n"
                              + _tail(output), output)
    return output


_MAKE_PERCENT = re.compile(r"^\[\s*(\d+)%\]")        # Makefiles: "[ 42%] Building C object ..."
_NINJA_COUNT = re.compile(r"^\[(\d+)/(\d+)\]")        # Ninja: "[3/24] Building C object ..."


def _run_with_progress(command: list[str], label: str) -> tuple[int, str]:
    """Run a build, showing the percentage its tool prints; (exit code, output)."""
    from fmubuilder.progress import progress
    lines = []
    with progress(100, label, unit="%") as bar:
        with subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) as proc:
            for line in proc.stdout:
                lines.append(line)
                percent = _build_percent(line)
                if percent is not None and percent > bar.done:
                    bar.advance(percent - bar.done)
        if proc.returncode != 0:
            bar.stop(f"failed (exit code {proc.returncode})")
        elif bar.done < 100:
            bar.advance(100 - bar.done)     # the tool printed no percentage for its last steps
    return proc.returncode, "".join(lines)


def _build_percent(line: str) -> int | None:
    make = _MAKE_PERCENT.match(line)
    if make:
        return int(make.group(1))
    ninja = _NINJA_COUNT.match(line)
    if ninja and int(ninja.group(2)) > 0:
        return 100 * int(ninja.group(1)) // int(ninja.group(2))
    return None


def _tail(text: str, lines: int = _LOG_TAIL_LINES) -> str:
    return "\n".join("    " + line for line in text.rstrip().splitlines()[-lines:])


# ---------------------------------------------------------------------------------------
# Example FMUs


# What the package needs besides its Python code. The checkout keeps them at the top level;
# an installed package carries a copy in fmubuilder/_data (setup.py copies them there).
DATA_ITEMS = ("CMakeLists.txt", "cmake", "c_templates", "examples")
INSTALLED_DATA_DIR = "_data"


def repo_root() -> pathlib.Path:
    """The folder holding CMakeLists.txt, cmake/, c_templates/ and examples/.

    That is the package's own copy when fmubuilder is installed from a wheel or with
    `pip install .`, else the source checkout the package sits in.
    """
    package = pathlib.Path(__file__).resolve().parent
    for root in (package / INSTALLED_DATA_DIR, package.parent):
        if all((root / item).exists() for item in DATA_ITEMS):
            return root
    raise FmuBuilderError(
        f"the C templates, CMake files and example sources are missing next to {package}: "
        "reinstall fmubuilder (pip install --force-reinstall fmubuilder) or use a complete source checkout")


def data_path(*parts: str) -> pathlib.Path:
    """A file or folder of the package data, e.g. data_path("c_templates")."""
    return repo_root().joinpath(*parts)


def list_examples() -> list[str]:
    """Names of the example FMUs, as declared with add_fmu(TARGET ...) in CMakeLists.txt."""
    text = (repo_root() / "CMakeLists.txt").read_text()
    text = re.sub(r"#[^\n]*", "", text)  # drop comments, including commented-out models
    return re.findall(r"\badd_fmu\s*\(\s*TARGET\s+([A-Za-z0-9_.+-]+)", text)


def example_fmu(name: str) -> pathlib.Path:
    """Path of the built example FMU ``name`` (e.g. "bouncing_ball"), building on demand."""
    examples = list_examples()
    if name not in examples:
        raise FmuBuilderError(f"unknown example FMU '{name}': choose one of {', '.join(examples)}")
    fmu_dir = _built_examples_dir()
    fmu = fmu_dir / f"{name}.fmu"
    if not fmu.is_file():
        log = fmu_dir / _FAILED_BUILD_LOG
        output = log.read_text(errors="replace") if log.is_file() else ""
        raise FmuBuilderError(
            f"example FMU '{name}' failed to build; fix its C sources in examples/ (compiler output below):\n"
            + _tail(_lines_about(output, name)))
    return fmu


def cache_dir() -> pathlib.Path:
    """Root of the build cache: $FMUBUILDER_CACHE or ~/.cache/fmubuilder."""
    configured = os.environ.get("FMUBUILDER_CACHE")
    root = pathlib.Path(configured) if configured else pathlib.Path.home() / ".cache" / "fmubuilder"
    return root.expanduser()


def examples_source_hash() -> str:
    """Hash of everything that goes into the example build (sources, headers, CMake files)."""
    root = repo_root()
    digest = hashlib.sha256(_CACHE_FORMAT.encode())
    digest.update(str(fmi_headers_dir()).encode())
    for path in _build_inputs(root):
        digest.update(str(path.relative_to(root)).encode() + b"\0")
        digest.update(path.read_bytes() + b"\0")
    return digest.hexdigest()[:20]


def _build_inputs(root: pathlib.Path) -> list[pathlib.Path]:
    def hidden(path: pathlib.Path) -> bool:
        return any(part.startswith(".") or part == "__pycache__" for part in path.relative_to(root).parts)
    found = [path for folder in (root / "cmake", root / "examples") for path in folder.rglob("*")
             if path.is_file() and not hidden(path)]
    return sorted([root / "CMakeLists.txt", *found])


def _built_examples_dir() -> pathlib.Path:
    """Folder with all example FMUs for the current sources; built once (cached_folder)."""
    return cached_folder(cache_dir() / "examples", examples_source_hash(), _build_examples)


def _build_examples(staged: pathlib.Path, scratch: pathlib.Path) -> None:
    build = build_cmake_project(repo_root(), scratch / "build", keep_going=True,
                                progress_label="building the example FMUs (once; cached)")
    for fmu in build.fmus():
        shutil.copy2(fmu, staged / fmu.name)
    if len(build.fmus()) < len(list_examples()):
        (staged / _FAILED_BUILD_LOG).write_text(build.output)


def cached_folder(cache: pathlib.Path, key: str, fill) -> pathlib.Path:
    """cache/key, made once by `fill(staged, scratch)` filling the empty folder `staged` (with
    room to work in `scratch`). Concurrent processes serialize on a lock file and the result
    appears by an atomic rename, so a reader never sees a half-written folder."""
    cache.mkdir(parents=True, exist_ok=True)
    final = cache / key
    if final.is_dir():
        return final
    with file_lock(cache / f".{key}.lock"):
        if final.is_dir():  # another process finished it while we waited
            return final
        with tempfile.TemporaryDirectory(prefix=f".{key}-", dir=cache) as scratch:
            staged = pathlib.Path(scratch) / "result"
            staged.mkdir()
            fill(staged, pathlib.Path(scratch))
            os.rename(staged, final)
    return final


@contextlib.contextmanager
def file_lock(path: pathlib.Path):
    """Hold an exclusive lock on ``path`` (created if missing) for the ``with`` block."""
    with open(path, "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def _lines_about(output: str, name: str) -> str:
    """The part of a build log that concerns one example (falls back to the whole log)."""
    relevant = [line for line in output.splitlines() if name in line or "error" in line.lower()]
    return "\n".join(relevant) if relevant else output
