"""Source FMUs: an FMU that ships its C sources but no binary for this machine is compiled
once (CMake, with the add_fmu() helper the examples use) into a cached copy that carries the
binary, and that copy is what gets extracted, simulated and exported.

Which files to compile comes from the FMU itself: ``sources/buildDescription.xml`` when it has
one, else the ``<SourceFiles>`` of its ``<ModelExchange>`` element. The cache is keyed by the
FMU's name and bytes and the CMake helper, so an unchanged FMU is compiled once per machine.
"""
from __future__ import annotations

import hashlib
import re
import sys
import zipfile
from dataclasses import dataclass
from pathlib import Path

from ..build import CMakeBuildError, build_cmake_project, cache_dir, cached_folder, data_path
from ..errors import FmuBuilderError, first_line
from .archive import (BUILD_DESCRIPTION, binary_entry, binary_platform, check_entry_inside, inflate_member,
                      max_extract_bytes, read_model_info)

# Bump when the compile flags or the cached layout change.
_CACHE_FORMAT = "1"
_CXX_SUFFIXES = (".cpp", ".cc", ".cxx", ".C")
_announced: set[tuple[Path, Path]] = set()


@dataclass(frozen=True)
class SourceBuild:
    """What the FMU says to compile; paths are relative to its sources/ folder."""

    files: tuple[str, ...]
    include_dirs: tuple[str, ...] = ()
    definitions: tuple[str, ...] = ()   # NAME or NAME=VALUE


def runnable_fmu(path: str | Path) -> Path:
    """``path`` itself when it carries a binary for this machine, else its compiled copy."""
    path = Path(path)
    if _has_platform_binary(path):
        return path  # the common case, checked without parsing; FmuArchive checks the rest
    info = read_model_info(path)  # every check, and the refusal of an FMU with neither binary nor sources
    with zipfile.ZipFile(path) as zf:
        if binary_entry(info.model_identifier) in zf.namelist():
            return path
    return compiled_fmu(path, info.model_identifier)


def _has_platform_binary(path: Path) -> bool:
    folder = f"binaries/{binary_platform()}/"
    try:
        with zipfile.ZipFile(path) as zf:
            return any(name.startswith(folder) and name.endswith(".so") for name in zf.namelist())
    except (OSError, zipfile.BadZipFile):
        return False  # read_model_info names the problem


def compiled_fmu(path: Path, model_identifier: str) -> Path:
    """The cached copy of the source FMU ``path`` with a binary for this machine (built on demand;
    concurrent processes wait for one build)."""
    def build_into(staged: Path, scratch: Path) -> None:
        library = _compile(path, model_identifier, scratch)
        _copy_with_binary(path, binary_entry(model_identifier), library, staged / path.name)
    target = cached_folder(cache_dir() / "source_fmus", _cache_key(path), build_into) / path.name
    _announce(path, target)
    return target


def declared_build(path: Path) -> SourceBuild:
    """The source files, include folders and definitions the FMU declares for Model Exchange."""
    from fmpy import read_model_description
    from fmpy.model_description import read_build_description

    md = read_model_description(str(path), validate=False)
    identifier = md.modelExchange.modelIdentifier
    with zipfile.ZipFile(path) as zf:
        has_build_description = BUILD_DESCRIPTION in zf.namelist()
    try:
        configurations = read_build_description(str(path), validate=False) if has_build_description \
            else md.buildConfigurations
    except Exception as exc:  # fmpy raises plain Exceptions for a bad file
        raise FmuBuilderError(f"{path}: cannot read {BUILD_DESCRIPTION} ({first_line(exc)})") from None
    matching = [c for c in configurations if c.modelIdentifier in (identifier, None)] or list(configurations)
    sets = [s for c in matching[:1] for s in c.sourceFileSets]
    files = tuple(f for s in sets for f in s.sourceFiles)
    if not files:
        raise FmuBuilderError(f"{path} has no binary for this machine and declares no source files to compile; "
                              "export it with a linux64 binary or with its C sources")
    return SourceBuild(
        files=files,
        include_dirs=tuple(d for s in sets for d in s.includeDirectories),
        definitions=tuple(d.name if d.value is None else f"{d.name}={d.value}"
                          for s in sets for d in s.preprocessorDefinitions),
    )


def _cache_key(path: Path) -> str:
    digest = hashlib.sha256(_CACHE_FORMAT.encode())
    digest.update(path.name.encode() + b"\0")  # the cached copy keeps the name
    digest.update(data_path("cmake", "fmu.cmake").read_bytes())
    with open(path, "rb") as file:
        while block := file.read(1 << 20):
            digest.update(block)
    return digest.hexdigest()[:20]


def _compile(path: Path, model_identifier: str, scratch: Path) -> bytes:
    """Compile the declared sources into the FMU's shared library; returns its bytes."""
    build_spec = declared_build(path)
    unpacked = scratch / "fmu"
    _extract_sources(path, unpacked)
    sources = unpacked / "sources"
    for name in build_spec.files:
        check_entry_inside(path, sources, name)
        if not (sources / name).is_file():
            raise FmuBuilderError(f"{path} declares the source file '{name}', which is not in its sources/ folder; "
                                  "the FMU is incomplete: export it again")
    for name in build_spec.include_dirs:
        check_entry_inside(path, sources, name)
    project = scratch / "project"
    project.mkdir()
    (project / "CMakeLists.txt").write_text(_cmake_project(unpacked, build_spec))
    try:
        build = build_cmake_project(project, scratch / "build")
    except CMakeBuildError as exc:
        first = _first_error(exc.output, unpacked)
        raise FmuBuilderError(f"{path} has no binary for this machine and compiling its sources failed: {first}; "
                              "fix the sources or export the FMU with a linux64 binary") from None
    with zipfile.ZipFile(build.fmus()[0]) as built:
        return built.read(binary_entry(model_identifier))


def _cmake_project(unpacked: Path, build_spec: SourceBuild) -> str:
    sources = unpacked / "sources"
    languages = "C CXX" if any(name.endswith(_CXX_SUFFIXES) for name in build_spec.files) else "C"
    arguments = [
        "TARGET source_fmu",
        f"MODEL_DESCRIPTION {_quote(unpacked / 'modelDescription.xml')}",
        "SOURCES " + " ".join(_quote(sources / name) for name in build_spec.files),
        "INCLUDE_DIRS " + " ".join(_quote(sources / name) for name in ("", *build_spec.include_dirs)),
    ]
    if build_spec.definitions:
        arguments.append("DEFINITIONS " + " ".join(_quote(d) for d in build_spec.definitions))
    return "\n".join([
        "cmake_minimum_required(VERSION 3.16)",
        f"project(source_fmu LANGUAGES {languages})",
        f"include({_quote(data_path('cmake', 'fmu.cmake'))})",
        "add_fmu(" + "\n        ".join(arguments) + ")",
        "",
    ])


def _quote(value: str | Path) -> str:
    """A CMake quoted argument (no variable references, no escapes interpreted)."""
    text = value.as_posix() if isinstance(value, Path) else value
    return '"' + re.sub(r'([\\"$;])', r"\\\1", text) + '"'


def _extract_sources(path: Path, target: Path) -> None:
    """modelDescription.xml and sources/, refusing entries that leave the folder, capped in size."""
    budget = [max_extract_bytes()]
    with zipfile.ZipFile(path) as zf:
        for member in zf.infolist():
            if member.is_dir() or not (member.filename == "modelDescription.xml"
                                       or member.filename.startswith("sources/")):
                continue
            dest = check_entry_inside(path, target, member.filename)
            dest.parent.mkdir(parents=True, exist_ok=True)
            with open(dest, "wb") as out:
                inflate_member(zf, member, path, out.write, budget)


def _copy_with_binary(path: Path, entry: str, library: bytes, target: Path) -> None:
    """The original FMU with the compiled library added as ``entry``."""
    with zipfile.ZipFile(path) as original, zipfile.ZipFile(target, "w", zipfile.ZIP_DEFLATED) as copy:
        for member in original.infolist():
            copy.writestr(member, original.read(member))
        copy.writestr(entry, library)


def _first_error(output: str, unpacked: Path) -> str:
    """The compiler's first error line, with the scratch folder cut from its file names."""
    lines = [line.strip() for line in output.splitlines() if line.strip()]
    chosen = next((line for line in lines if re.search(r"\berror:|CMake Error|undefined reference", line)),
                  lines[-1] if lines else "no output")
    return chosen.replace(unpacked.as_posix() + "/", "")


def _announce(path: Path, compiled: Path) -> None:
    """Say once per process which binary a source FMU runs with."""
    key = (path.resolve(), compiled)
    if key not in _announced:
        _announced.add(key)
        print(f"note: {path} has no binary for this machine; using one compiled from its sources ({compiled})",
              file=sys.stderr)
