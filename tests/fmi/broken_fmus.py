"""Make broken variants of a good FMU, one defect each."""
import re
import zipfile
from pathlib import Path


def rewrite_fmu(source: Path, target: Path, *, xml=None, drop=()) -> Path:
    """Copy an FMU, optionally transforming modelDescription.xml and dropping entries."""
    with zipfile.ZipFile(source) as zin, zipfile.ZipFile(target, "w") as zout:
        for item in zin.infolist():
            if any(item.filename.startswith(prefix) for prefix in drop):
                continue
            data = zin.read(item.filename)
            if item.filename == "modelDescription.xml" and xml is not None:
                data = xml(data.decode()).encode()
            zout.writestr(item, data)
    return target


def set_fmi_version(version: str):
    return lambda text: text.replace('fmiVersion="2.0"', f'fmiVersion="{version}"', 1)


def co_simulation_only(text: str) -> str:
    return re.sub(r"<ModelExchange\b", "<CoSimulation", text, count=1).replace("</ModelExchange>", "</CoSimulation>")
