"""Export an FMU whose parameters are calibrated: the original, with new values that it applies itself.

    export_calibrated("plant.fmu", {"b": 0.2}, "plant_calibrated.fmu")

A new start value alone does not make a valid FMU: the binary keeps its own value, and an
importer that sets no start values (fmpy's default) simulates the old one. So the original goes
whole beside a small library, `<id>_calibrated.so` (c_templates/calibrated_fmu.c, see the README's
"The candidates") that forwards every call; the modelDescription.xml gets the new start values, a
new GUID and modelIdentifier, and no SourceFiles. The export runs fmpy's validation on the result.

`validate_calibrated` is the round trip: fmpy running the calibrated FMU without start values
against fmpy and fmubuilder's replica of fmpy's Euler loop running the original with them.
"""
from __future__ import annotations

import subprocess
import tempfile
import zipfile
from pathlib import Path

import numpy as np
from lxml import etree

from fmubuilder.build import data_path
from fmubuilder.errors import FmuBuilderError
from fmubuilder.files import copy_atomically
from fmubuilder.fmi.archive import PLATFORM     # the calibration library is built for linux64 only

from .c_text import c_string
from .hybrid_description import new_identity
from .wrapper import check_model_identifier, check_output_fmu, check_with_fmpy

SOURCE = data_path("c_templates", "calibrated_fmu.c")
SUFFIX = "_calibrated"
# Round trip: fmpy on the calibrated FMU against the original with the values, same solver and step.
ROUNDTRIP_TOLERANCE = 1e-9


def export_calibrated(original_fmu, parameters: dict[str, float], output_fmu, force: bool = False) -> Path:
    """Write the original FMU with `parameters` ({name: value}) calibrated to `output_fmu`."""
    from fmubuilder.fmi import read_model_info
    original_fmu, output = Path(original_fmu), check_output_fmu(output_fmu, force)
    if not parameters:
        raise FmuBuilderError("no calibrated parameters given; give at least one {name: value}")
    info = read_model_info(original_fmu)
    check_model_identifier(info.model_identifier, original_fmu)
    overrides = _overrides(info, parameters)
    identifier = info.model_identifier + SUFFIX
    with tempfile.TemporaryDirectory(prefix="fmubuilder-calibrated-") as scratch:
        scratch = Path(scratch)
        with zipfile.ZipFile(original_fmu) as original:
            inner_binary = f"binaries/{PLATFORM}/{info.model_identifier}.so"
            if inner_binary not in original.namelist():
                raise FmuBuilderError(f"{original_fmu} has no {inner_binary}; export it for {PLATFORM}")
            xml, guid = calibrated_description(original.read("modelDescription.xml"), identifier, overrides)
            library = _compile(scratch, f"{info.model_identifier}.so", identifier, guid, info.guid, overrides)
            packed = scratch / "calibrated.fmu"
            _pack(original, packed, xml, library, identifier)
        check_with_fmpy(packed, original_fmu)
        output.parent.mkdir(parents=True, exist_ok=True)
        copy_atomically(packed, output)
    return output


def _overrides(info, parameters: dict[str, float]) -> list[tuple[str, int, float]]:
    """(name, value reference, value) per calibrated parameter, checked against the FMU."""
    overrides = []
    for name, value in parameters.items():
        var = info.variable(name)   # an unknown name fails here with a suggestion
        if var.type != "Real" or var.causality != "parameter" or var.variability not in ("fixed", "tunable"):
            raise FmuBuilderError(f"'{name}' is a {var.causality} {var.type} ({var.variability}); only a Real "
                                  "parameter (fixed or tunable) can be calibrated")
        value = float(value)
        if not np.isfinite(value):
            raise FmuBuilderError(f"the calibrated value of '{name}' is {value}; give a finite number")
        overrides.append((name, var.value_reference, value))
    return overrides


def calibrated_description(original_xml: bytes, identifier: str,
                           overrides: list[tuple[str, int, float]]) -> tuple[bytes, str]:
    """The original's modelDescription.xml with the calibrated start values and a new identity,
    and its new GUID."""
    root = etree.fromstring(original_xml)
    values = {name: value for name, _, value in overrides}
    guid = new_identity(root)
    calibrated = ", ".join(f"{name} = {value:.6g}" for name, value in values.items())
    root.set("description", f"{root.get('description') or root.get('modelName')} (calibrated: {calibrated})")
    for kind in ("ModelExchange", "CoSimulation"):
        for element in root.findall(kind):
            element.set("modelIdentifier", identifier)
            for sources in element.findall("SourceFiles"):
                element.remove(sources)
    for variable in root.find("ModelVariables").findall("ScalarVariable"):
        if variable.get("name") in values:
            variable.find("Real").set("start", repr(values[variable.get("name")]))
    return etree.tostring(root, xml_declaration=True, encoding="UTF-8", pretty_print=True), guid


def _compile(scratch: Path, inner: str, identifier: str, guid: str, inner_guid: str,
             overrides: list[tuple[str, int, float]]) -> Path:
    from fmubuilder.build import c_compiler, fmi_headers_dir
    compiler = c_compiler()
    headers = fmi_headers_dir()
    if headers is None:
        raise FmuBuilderError("fmpy's FMI 2.0 headers are missing; reinstall fmpy (pip install --force-reinstall fmpy)")
    library = scratch / f"{identifier}.so"
    definitions = {
        "CALIBRATED_GUID": c_string(guid), "INNER_GUID": c_string(inner_guid),
        "INNER_LIBRARY": c_string(inner), "N_OVERRIDES": str(len(overrides)),
        "OVERRIDE_VRS": "{" + ", ".join(f"{vr}u" for _, vr, _ in overrides) + "}",
        "OVERRIDE_VALUES": "{" + ", ".join(repr(v) for _, _, v in overrides) + "}",
        "OVERRIDE_NAMES": "{" + ", ".join(c_string(name) for name, _, _ in overrides) + "}",
    }
    command = [compiler, "-shared", "-fPIC", "-O2", "-Wall", "-I", str(headers),
               *[f"-D{key}={value}" for key, value in definitions.items()],
               str(SOURCE), "-o", str(library), "-ldl"]
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0:
        raise FmuBuilderError(f"compiling the calibrated FMU's library failed: {done.stderr.strip()[-2000:]}")
    return library


def _pack(original: zipfile.ZipFile, packed: Path, xml: bytes, library: Path, identifier: str) -> None:
    """Every file of the original except its description, sources and other platforms' binaries
    (the calibration library exists for linux64 only), plus the library beside the binary."""
    with zipfile.ZipFile(packed, "w", zipfile.ZIP_DEFLATED) as out:
        out.writestr("modelDescription.xml", xml)
        for member in original.infolist():
            name = member.filename
            if member.is_dir() or name == "modelDescription.xml" or name.startswith("sources/"):
                continue
            if name.startswith("binaries/") and not name.startswith(f"binaries/{PLATFORM}/"):
                continue
            out.writestr(member, original.read(member))
        info = zipfile.ZipInfo(f"binaries/{PLATFORM}/{identifier}.so")
        info.external_attr = 0o755 << 16
        info.compress_type = zipfile.ZIP_DEFLATED
        out.writestr(info, library.read_bytes())


# -- round trip ---------------------------------------------------------------------------------

def validate_calibrated(calibrated_fmu, original_fmu, parameters: dict[str, float], *, start_values=None,
                        start_time: float = 0.0, stop_time: float, step_size: float) -> dict:
    """fmpy (Euler) on the calibrated FMU without the calibrated values against fmpy and
    fmubuilder's replica of fmpy's Euler loop on the original with them: the same binary and
    arithmetic, so equal to round-off.
    Returns {"passed", "max_rel_error", "rows", "table"}."""
    from fmubuilder.fmi import read_model_info
    from fmubuilder.fmi.instance import Fmu
    from fmubuilder.simulation import FmuSystem

    from .validate import simulate_fmpy_euler, simulate_with_fmpy
    info = read_model_info(original_fmu)
    start_values = dict(start_values or {})
    names = [v.name for v in info.variables.values() if v.type == "Real" and v.causality == "output"] \
        or [s.name for s in info.states]
    names += [name for name in parameters if name not in names]
    common = dict(start_time=start_time, stop_time=stop_time, output_interval=step_size, output=names)

    def fmpy_run(fmu, starts):
        return simulate_with_fmpy(fmu, solver="Euler", step_size=step_size, start_values=starts, validate=False,
                                  **common)

    calibrated = fmpy_run(calibrated_fmu, start_values)
    original = fmpy_run(original_fmu, {**start_values, **parameters})
    # fmubuilder's replica of fmpy's Euler loop (export/validate.py) on the original, in the engine's
    # FMU access: independent of fmpy's binding, same event handling as fmpy's loop.
    with Fmu(original_fmu) as fmu:
        system = FmuSystem(fmu, variables=names, start_values={**start_values, **parameters})
        try:
            replica = simulate_fmpy_euler(system, start_time, stop_time, step_size)
        finally:
            system.close()
    rows = [_compare("fmpy Euler: calibrated FMU vs original with the values", calibrated, original, names),
            _compare("fmpy Euler (calibrated FMU) vs fmubuilder's fmpy-Euler loop (original with the values)",
                     calibrated, {"time": replica.time, **replica.values}, names)]
    worst = max(r["max_rel"] for r in rows)
    table = "\n".join(f"{r['label']}: max relative difference {r['max_rel']:.3g} over {r['samples']} samples"
                      for r in rows)
    return {"passed": bool(worst <= ROUNDTRIP_TOLERANCE), "max_rel_error": worst, "rows": rows, "table": table}


def _compare(label: str, a, b, names) -> dict:
    """Largest difference relative to each signal's range, on the time stamps both runs share."""
    ta, tb = np.asarray(a["time"], float), np.asarray(b["time"], float)
    # Keep one sample per time (the last: after an event), then the stamps both have.
    ka, kb = np.r_[np.diff(ta) > 0, True], np.r_[np.diff(tb) > 0, True]
    shared, ia, ib = np.intersect1d(np.round(ta[ka], 9), np.round(tb[kb], 9), return_indices=True)
    worst = 0.0
    for name in names:
        va, vb = np.asarray(a[name], float)[ka][ia], np.asarray(b[name], float)[kb][ib]
        scale = max(float(np.max(np.abs(va))) if va.size else 0.0, 1e-12)
        worst = max(worst, float(np.max(np.abs(va - vb))) / scale if va.size else float("inf"))
    return {"label": label, "max_rel": worst, "samples": int(shared.size)}
