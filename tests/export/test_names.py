"""Unusual but legal names export: Modelica quoted identifiers, array elements, quotes, comment
ends, backslashes, spaces and non-ASCII in variable and model names reach the C configuration,
the modelDescription and the round trip intact; an illegal modelIdentifier is one clear error."""
from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

import fmpy
import numpy as np
import pytest
from fmpy.validation import validate_fmu

from fmubuilder.build import build_cmake_project
from fmubuilder.errors import FmuBuilderError
from fmubuilder.export import HybridSpec, validate_hybrid
from fmubuilder.export.c_text import c_comment
from fmubuilder.fmi import read_model_info

from .test_wrapper import make_hybrid, make_network

HERE = Path(__file__).resolve().parent
MY_VAR, A1 = "'my var'", "a[1]"
RATE = "'k */ (rate) \\\"fast\\\"'"
OUTPUT = "'y <out> ${x} $(y); #@% [1]'"
# Flat naming allows any text; these replace RATE and OUTPUT in the flat variant.
FLAT_NAMES = {RATE: 'k "rate" */ \\n µ', OUTPUT: "y <out> ${x} $(y) ; # @ % ' \\"}


@pytest.fixture(scope="module")
def odd_original(tmp_path_factory) -> Path:
    build = build_cmake_project(HERE / "odd_names", tmp_path_factory.mktemp("odd_names_build"))
    return build.fmus()[0]


def xml_escaped(text: str) -> str:
    return text.replace("&", "&amp;").replace('"', "&quot;").replace("<", "&lt;").replace(">", "&gt;")


def rewritten(original: Path, target: Path, edit, binary_name: str | None = None) -> Path:
    """A copy of `original` with its modelDescription edited (and its binary renamed)."""
    with zipfile.ZipFile(original) as source, zipfile.ZipFile(target, "w") as copy:
        for item in source.infolist():
            data, name = source.read(item), item.filename
            if name == "modelDescription.xml":
                data = edit(data.decode()).encode()
            elif binary_name and name.startswith("binaries/"):
                name = str(Path(name).with_name(binary_name + ".so"))
            copy.writestr(name, data)
    return target


def flat_variant(original: Path, target: Path) -> Path:
    def edit(xml: str) -> str:
        xml = xml.replace('variableNamingConvention="structured"', 'variableNamingConvention="flat"')
        for structured, flat in FLAT_NAMES.items():
            xml = xml.replace(f'name="{xml_escaped(structured)}"', f'name="{xml_escaped(flat)}"')
        return xml
    return rewritten(original, target, edit)


def export_and_check(original: Path, folder: Path, rate: str, output: str):
    inputs = [MY_VAR, A1, "der(a[1])", rate, output]
    spec, fmu = make_hybrid(folder, original, ["der('my var')", "der(a[1])"], inputs, seed=7,
                            aliases={output: "der(a[1])"})
    assert validate_fmu(str(fmu)) == []
    info = read_model_info(fmu)
    assert {MY_VAR, A1, rate, output} <= set(info.variables)
    # The names reach the C configuration as escaped strings and defused comments.
    with zipfile.ZipFile(fmu) as archive:
        config = archive.read("sources/hybrid_config.h").decode()
    assert "\"der('my var')\"" in config
    assert c_comment(rate) in config and "*/" in rate and rate not in config
    # The round trip against the Python reference (fmpy Euler and CVode, the engine).
    report = validate_hybrid(fmu, spec)
    assert report.passed, report
    result = fmpy.simulate_fmu(str(fmu), stop_time=1.0, output=[MY_VAR, output])
    assert np.all(np.isfinite(result[output]))
    return spec, fmu


def test_structured_quoted_and_array_names_export(odd_original, tmp_path):
    export_and_check(odd_original, tmp_path, RATE, OUTPUT)


def test_flat_names_with_any_characters_export(odd_original, tmp_path):
    flat = flat_variant(odd_original, tmp_path / "odd_names_flat.fmu")
    assert validate_fmu(str(flat)) == []
    export_and_check(flat, tmp_path / "hybrid", FLAT_NAMES[RATE], FLAT_NAMES[OUTPUT])


def test_a_model_name_with_quotes_and_comment_ends_exports(odd_original, tmp_path):
    info = read_model_info(odd_original)
    assert '"' in info.model_name and "*/" in info.model_name and "\\" in info.model_name
    spec, fmu = make_hybrid(tmp_path, odd_original, ["der(a[1])"], [MY_VAR, A1], seed=8)
    assert read_model_info(fmu).model_name == info.model_name + "_hybrid"


@pytest.mark.parametrize("identifier", ["odd-names", "2odd", "odd names", 'odd"x', "int", "odd.names"])
def test_an_illegal_model_identifier_is_one_clear_error(odd_original, tmp_path, identifier):
    escaped = xml_escaped(identifier)
    illegal = rewritten(odd_original, tmp_path / "illegal.fmu",
                        lambda xml: xml.replace('modelIdentifier="odd_names"', f'modelIdentifier="{escaped}"'),
                        binary_name=identifier)
    info = read_model_info(illegal)
    assert info.model_identifier == identifier
    spec = HybridSpec(original_fmu=illegal, original_guid=info.guid, channels=["der(a[1])"], inputs=[A1],
                      onnx=make_network(tmp_path / "network.onnx", 1, 1, seed=0))
    spec_path = spec.save(tmp_path / "spec.json")
    with pytest.raises(FmuBuilderError, match="is not a C identifier"):
        from fmubuilder.export import export_hybrid
        export_hybrid(spec_path, tmp_path / "hybrid.fmu")
    proc = subprocess.run([sys.executable, "-m", "fmubuilder.cli", "export", str(spec_path), "-o",
                           str(tmp_path / "hybrid.fmu")], capture_output=True, text=True, timeout=300)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode != 0 and len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    assert "is not a C identifier" in lines[0] and not (tmp_path / "hybrid.fmu").exists()
