"""Export a hybrid model as an FMI 2.0 Model-Exchange FMU that wraps the original FMU.

    export_hybrid("hybrid_spec.json", "plant_hybrid.fmu")

Steps, all inside a temporary folder: render the wrapper's configuration header (the tables the
static c_templates/hybrid_wrapper.c reads) and the network kernel, derive modelDescription.xml,
stage the resources (the original's binaries folder beside its own resources, the binary as
resources/<id>.so; under resources/fmubuilder_hybrid/ what validates the FMU on its own), build
with add_fmu() (cmake/fmu.cmake), carry documentation/ and extra/, check with fmpy, move into place.

When the original also carries binaries/win64/<id>.dll, the same project is built a second time
with mingw-w64 (cmake/mingw-w64-x86_64.cmake) and the hybrid gains binaries/win64/: its wrapper
DLL beside copies of the original's win64 files, which the wrapper loads from there. The
original's resources/ serve both platforms.
"""
from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
import tempfile
import zipfile
from pathlib import Path

from fmubuilder.build import data_path
from fmubuilder.errors import FmuBuilderError
from fmubuilder.files import copy_atomically

from .c_text import C_IDENTIFIER, TEMPLATE_DIR, c_double, templates
from .hybrid_description import HybridDescription, derive_model_description
from .spec import HybridSpec

FMU_CMAKE = data_path("cmake", "fmu.cmake")
MINGW_TOOLCHAIN = FMU_CMAKE.with_name("mingw-w64-x86_64.cmake")
MINGW_COMPILER = "x86_64-w64-mingw32-gcc"
WIN64 = "win64"
KERNEL_PREFIX = "hybrid_ann"
WRAPPER_SOURCE = "hybrid_wrapper.c"
# The wrapper's static files, copied as they are, and its generated configuration.
STATIC_HEADERS = ("hybrid_tables.h",)
CONFIG_HEADER = "hybrid_config.h"
# Inside resources/: what validation needs to rebuild the reference without the spec file.
EMBEDDED_DIR = "fmubuilder_hybrid"
EMBEDDED_SPEC = "hybrid_spec.json"
EMBEDDED_ONNX = "network.onnx"
EMBEDDED_ORIGINAL_XML = "original_modelDescription.xml"
# Folders of the original FMU the hybrid carries unchanged.
CARRIED_FOLDERS = ("documentation", "extra")
_INPUT_GROUPS = {"Real": "real", "Integer": "integer", "Enumeration": "integer", "Boolean": "boolean"}
_C_KEYWORDS = frozenset(
    "auto break case char const continue default do double else enum extern float for goto if inline int long "
    "register restrict return short signed sizeof static struct switch typedef union unsigned void volatile while "
    "_Alignas _Alignof _Atomic _Bool _Complex _Generic _Imaginary _Noreturn _Static_assert _Thread_local".split())


def export_hybrid(spec_or_path: HybridSpec | str | os.PathLike, output_fmu: str | os.PathLike,
                  force: bool = False, win64: bool | None = None) -> Path:
    """Build the hybrid FMU described by a HybridSpec (or its JSON file) at `output_fmu`.

    `win64`: also build the Windows binaries (the original must carry binaries/win64 and
    mingw-w64 must be installed); None (default) does so when both hold, False never.
    Refuses to overwrite an existing file unless `force`. Returns the output path.
    """
    spec = spec_or_path if isinstance(spec_or_path, HybridSpec) else HybridSpec.load(spec_or_path)
    output = check_output_fmu(output_fmu, force)
    if not output.parent.is_dir():
        raise FmuBuilderError(f"cannot write {output}: folder {output.parent} does not exist; create it first")

    from fmubuilder.fmi import read_model_info
    info = read_model_info(spec.original_fmu)
    check_model_identifier(info.model_identifier, spec.original_fmu)
    spec.check(info)
    with_win64 = _wants_win64(spec.original_fmu, info, win64)
    with tempfile.TemporaryDirectory(prefix="fmubuilder-export-") as scratch:
        scratch = Path(scratch)
        built = _build(spec, info, scratch, with_win64)
        check_with_fmpy(built, spec.original_fmu)
        copy_atomically(built, output)
    return output


def check_output_fmu(output_fmu, force: bool) -> Path:
    output = Path(output_fmu)
    if output.suffix.lower() != ".fmu":
        raise FmuBuilderError(f"{output}: the output file must end in .fmu")
    if output.exists() and not force:
        raise FmuBuilderError(f"{output} exists; choose another name or overwrite it with --force (force=True)")
    return output


def check_model_identifier(identifier: str, fmu) -> None:
    """FMI 2.0 requires the modelIdentifier to be a C identifier; the hybrid's is derived from it."""
    if not C_IDENTIFIER.match(identifier) or identifier in _C_KEYWORDS:
        raise FmuBuilderError(
            f"{fmu}: the modelIdentifier {identifier!r} is not a C identifier (FMI 2.0 requires letters, digits and "
            "'_', not starting with a digit, and no C keyword); re-export the original FMU with a valid one")


def _build(spec: HybridSpec, info, scratch: Path, with_win64: bool = False) -> Path:
    """Stage the CMake project in scratch/project, build it, return the packed FMU."""
    from fmubuilder.build import build_cmake_project
    from fmubuilder.fmi.sources import runnable_fmu
    from fmubuilder.export.kernel import generate_kernel

    project = scratch / "project"
    (project / "sources").mkdir(parents=True)
    # A source FMU's compiled copy: the hybrid carries the binary built from its sources.
    with zipfile.ZipFile(runnable_fmu(spec.original_fmu)) as original:
        original_xml = original.read("modelDescription.xml")
        description = derive_model_description(original_xml, spec, info)
        binaries = _stage_resources(original, info, project / "resources")
    (project / "modelDescription.xml").write_bytes(description.xml)
    _embed_for_validation(spec, description, original_xml, binaries, project / "resources" / EMBEDDED_DIR)

    sources, headers = [WRAPPER_SOURCE], [CONFIG_HEADER, *STATIC_HEADERS]
    if spec.channels:       # a hybrid of overrides alone runs no network
        kernel = generate_kernel(spec.onnx, prefix=KERNEL_PREFIX)
        kernel.write(project / "sources")
        sources.append(kernel.source_name)
        headers.append(kernel.header_name)
    for name in (WRAPPER_SOURCE, *STATIC_HEADERS):
        shutil.copyfile(TEMPLATE_DIR / name, project / "sources" / name)
    (project / "sources" / CONFIG_HEADER).write_text(render_config(spec, info, description))
    (project / "CMakeLists.txt").write_text(_render("hybrid_CMakeLists.txt.j2", {
        "identifier": description.model_identifier,
        "fmu_cmake": FMU_CMAKE.as_posix(),
        "sources": [f"sources/{name}" for name in sources],
        "headers": [f"sources/{name}" for name in headers],
    }))
    build = build_cmake_project(project, scratch / "build",
                                progress_label=f"export: compiling {description.model_identifier}.fmu")
    fmu = build.build_dir / "fmus" / f"{description.model_identifier}.fmu"
    if not fmu.is_file():
        raise FmuBuilderError(f"the build produced no {fmu.name}; see the CMake output:\n{build.output[-2000:]}")
    if with_win64:
        _add_win64_binaries(project, scratch / "build-win64", spec.original_fmu, description.model_identifier, fmu)
    _carry_folders(spec.original_fmu, fmu)
    return fmu


def original_win64_library(fmu: Path, info) -> str | None:
    """The entry binaries/win64/<id>.dll of an FMU, or None when it has none."""
    entry = f"binaries/{WIN64}/{info.model_identifier}.dll"
    with zipfile.ZipFile(fmu) as archive:
        return entry if entry in archive.namelist() else None


def mingw_missing() -> str | None:
    """Why the win64 wrapper cannot be cross-compiled here, or None when it can."""
    if shutil.which(MINGW_COMPILER) is None:
        return f"{MINGW_COMPILER} not found; install mingw-w64 (Debian: apt-get install gcc-mingw-w64-x86-64)"
    return None


def _wants_win64(original_fmu: Path, info, requested: bool | None) -> bool:
    if requested is False:
        return False
    has_win64 = original_win64_library(original_fmu, info) is not None
    missing_tool = mingw_missing()
    if requested is None:
        return has_win64 and missing_tool is None
    if not has_win64:
        raise FmuBuilderError(f"{original_fmu} has no binaries/{WIN64}/{info.model_identifier}.dll; a win64 hybrid "
                              "wraps the original's win64 binary, so export the original for win64 as well")
    if missing_tool is not None:
        raise FmuBuilderError(f"cannot build the win64 binaries: {missing_tool}")
    return True


def _add_win64_binaries(project: Path, build_dir: Path, original_fmu: Path, identifier: str, hybrid_fmu: Path) -> None:
    """Cross-compile the wrapper for win64 and add it with the original's win64 files to the hybrid."""
    from fmubuilder.build import build_cmake_project
    build = build_cmake_project(project, build_dir, definitions={"CMAKE_TOOLCHAIN_FILE": MINGW_TOOLCHAIN.as_posix()})
    folder = f"binaries/{WIN64}/"
    wrapper_entry = f"{folder}{identifier}.dll"
    with zipfile.ZipFile(build.build_dir / "fmus" / f"{identifier}.fmu") as built:
        if wrapper_entry not in built.namelist():
            raise FmuBuilderError(f"the win64 build produced no {wrapper_entry}; see the CMake output:\n"
                                  f"{build.output[-2000:]}")
        wrapper_dll = built.read(wrapper_entry)
    with zipfile.ZipFile(original_fmu) as original, \
            zipfile.ZipFile(hybrid_fmu, "a", zipfile.ZIP_DEFLATED) as hybrid:
        hybrid.writestr(wrapper_entry, wrapper_dll)
        for member in original.infolist():
            if not member.filename.startswith(folder) or member.is_dir():
                continue
            if member.filename == wrapper_entry:
                raise FmuBuilderError(f"the original FMU has {member.filename}, the name of the hybrid's own win64 "
                                      "binary; rename that file in the original FMU")
            hybrid.writestr(member, original.read(member))


def built_platforms(fmu: Path) -> list[str]:
    """The platforms an FMU carries a binary for (the folders under binaries/)."""
    from fmubuilder.fmi.archive import binary_platforms
    with zipfile.ZipFile(fmu) as archive:
        return binary_platforms(archive.namelist())


def platform_note(original_fmu: Path, hybrid_fmu: Path) -> str:
    """One line for the user: the hybrid's platforms, and what would add the original's others."""
    from fmubuilder.fmi import read_model_info
    note = f"binaries: {', '.join(built_platforms(hybrid_fmu))}"
    original_has_win64 = original_win64_library(original_fmu, read_model_info(original_fmu)) is not None
    if original_has_win64 and WIN64 not in built_platforms(hybrid_fmu) and mingw_missing():
        note += f"; the original also has {WIN64}, but {mingw_missing()}"
    return note


def _carry_folders(original_fmu: Path, hybrid_fmu: Path) -> None:
    """The original's documentation/ (with its licences) and extra/ into the hybrid, as they are."""
    with zipfile.ZipFile(original_fmu) as original, zipfile.ZipFile(hybrid_fmu, "a", zipfile.ZIP_DEFLATED) as hybrid:
        present = set(hybrid.namelist())
        for member in original.infolist():
            if member.filename.split("/")[0] in CARRIED_FOLDERS and not member.is_dir() \
                    and member.filename not in present:
                hybrid.writestr(member, original.read(member))


def render_config(spec: HybridSpec, info, description: HybridDescription) -> str:
    """The wrapper's configuration header for `spec` on the original FMU `info`."""
    groups = {name: {"type": name, "vrs": [], "positions": [], "names": []} for name in ("real", "integer", "boolean")}
    derivative_inputs = {"states": [], "positions": []}
    derivative_names = {d.name for d in info.derivatives}
    for position, name in enumerate(spec.inputs):
        if name in derivative_names:
            derivative_inputs["states"].append(info.state_index(name))
            derivative_inputs["positions"].append(position)
            continue
        var = info.variable(name)
        group = groups[_INPUT_GROUPS[var.type]]
        group["vrs"].append(var.value_reference)
        group["names"].append(name)
        group["positions"].append(position)
    channels = [{
        "name": c.channel, "der_vr": c.der_vr, "state_index": c.state_index,
        "p_ann_vr": c.p_ann_vr, "p_fmu_vr": c.p_fmu_vr, "ann_vr": c.ann_vr,
        "p_ann_start": c_double(spec.p_ann[i]), "p_fmu_start": c_double(spec.p_fmu[i]),
        "p_ann": c.p_ann, "p_fmu": c.p_fmu, "ann": c.ann,
    } for i, c in enumerate(description.channels)]
    aliases = [{"name": name, "vr": info.variable(name).value_reference, "channel": spec.channels.index(channel)}
               for name, channel in spec.aliases.items()]
    overrides = [{"name": name, "vr": info.variable(name).value_reference, "value": c_double(value)}
                 for name, value in spec.overrides.items()]
    caps = info.capabilities
    return _render("hybrid_config.h.j2", {
        "identifier": description.model_identifier,
        "guid": description.guid,
        "inner_identifier": info.model_identifier,
        "inner_guid": info.guid,
        "inner_library": f"{info.model_identifier}.so",
        "inner_library_win64": f"{info.model_identifier}.dll",
        "n_states": info.n_states,
        "n_event_indicators": info.n_event_indicators,
        "n_ann_inputs": len(spec.inputs),
        "channels": channels,
        "aliases": aliases,
        "overrides": overrides,
        "input_groups": list(groups.values()),
        "derivative_inputs": derivative_inputs,
        "inner_log_categories": description.log_categories,
        "can_get_and_set_fmu_state": caps.can_get_and_set_fmu_state,
        "can_serialize_fmu_state": caps.can_get_and_set_fmu_state and caps.can_serialize_fmu_state,
        "can_not_use_memory_management_functions": _declares(spec.original_fmu, "canNotUseMemoryManagementFunctions"),
        "kernel_prefix": KERNEL_PREFIX if spec.channels else None,
        "kernel_header": f"{KERNEL_PREFIX}.h",
    })


def _declares(fmu: Path, capability: str) -> bool:
    """Whether the original's ModelExchange element sets a boolean capability flag to true."""
    import fmpy
    model_exchange = fmpy.read_model_description(str(fmu), validate=False).modelExchange
    return bool(getattr(model_exchange, capability, False))


def _render(template: str, context: dict) -> str:
    return templates().get_template(template).render(context)


def _stage_resources(original: zipfile.ZipFile, info, resources: Path) -> list[str]:
    """resources/ = the original's resources + its binaries/<platform>/ folder, the binary as <id>.so.

    Returns the files of the binaries folder (paths relative to it)."""
    from fmubuilder.fmi.archive import binary_platform
    resources.mkdir(parents=True)
    library = f"{info.model_identifier}.so"
    binaries = f"binaries/{binary_platform()}/"
    if binaries + library not in original.namelist():
        raise FmuBuilderError(f"the original FMU has no {binaries}{library}; export it for {binary_platform()}")
    staged = {}
    for member in original.infolist():
        if member.is_dir():
            continue
        for folder in ("resources/", binaries):
            if member.filename.startswith(folder):
                relative = member.filename[len(folder):]
                _check_resource_name(relative, member.filename, library, staged)
                staged[relative] = member
    for relative, member in staged.items():
        target = (resources / relative).resolve()
        if resources.resolve() not in target.parents:
            raise FmuBuilderError(f"the original FMU's entry {member.filename} points outside its folder; "
                                  "the FMU is corrupt")
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(original.read(member))
        if member.filename.startswith(binaries):
            target.chmod(0o755)
    return sorted(relative for relative, member in staged.items() if member.filename.startswith(binaries))


def _check_resource_name(relative: str, entry: str, library: str, staged: dict) -> None:
    """The hybrid's resources/ holds the original's resources and binaries side by side: no clashes."""
    if relative.split("/")[0] == EMBEDDED_DIR or (relative == library and entry.startswith("resources/")):
        raise FmuBuilderError(
            f"the original FMU has {entry}, a name the hybrid FMU needs for itself in resources/; "
            "rename that resource in the original FMU")
    if relative in staged:
        raise FmuBuilderError(
            f"the original FMU has both {staged[relative].filename} and {entry}, which the hybrid FMU keeps side by "
            "side in resources/; rename one of them in the original FMU")


def _embed_for_validation(spec: HybridSpec, description: HybridDescription, original_xml: bytes,
                          binaries: list[str], folder: Path) -> None:
    folder.mkdir(parents=True)
    if spec.onnx is not None:
        shutil.copyfile(spec.onnx, folder / EMBEDDED_ONNX)
    (folder / EMBEDDED_ORIGINAL_XML).write_bytes(original_xml)
    # Paths relative to the folder: validation rebuilds the original FMU beside the network.
    data = dataclasses.replace(spec, original_fmu=Path("original.fmu"),
                               onnx=Path(EMBEDDED_ONNX) if spec.onnx is not None else None).to_dict()
    data["gates"] = [{"channel": c.channel, "p_ann": c.p_ann, "p_fmu": c.p_fmu, "ann": c.ann}
                     for c in description.channels]
    # Which files of resources/ came from the original's binaries folder (to rebuild the original).
    data["original_binaries"] = binaries
    (folder / EMBEDDED_SPEC).write_text(json.dumps(data, indent=2) + "\n")


def check_with_fmpy(fmu: Path, original: Path) -> None:
    """fmpy's validation of the hybrid, except for problems the original has as well (the hybrid
    keeps the original's variables as they are)."""
    from fmpy.validation import validate_fmu
    problems = validate_fmu(str(fmu))
    if problems:
        inherited = {_without_line_numbers(p) for p in validate_fmu(str(original))}
        problems = [p for p in problems if _without_line_numbers(p) not in inherited]
    if problems:
        raise FmuBuilderError(
            "the generated hybrid FMU fails fmpy's validation (a bug in fmubuilder's export, please report it): "
            + "; ".join(problems))


def _without_line_numbers(problem: str) -> str:
    return re.sub(r"\(line \d+\)|line \d+", "", problem)

