"""Open an FMU file: check that it is an FMI 2.0 Model-Exchange FMU we can run, extract it.

Every way an FMU can be unusable ends here in one FmuBuilderError that names the problem
and what to do, so the stages behind this never see a half-valid FMU.
"""
from __future__ import annotations

import platform
import shutil
import sys
import tempfile
import weakref
import zipfile
from pathlib import Path

from ..errors import FmuBuilderError
from .model import ModelInfo, model_info_from_fmpy

PLATFORM = "linux64"


def binary_platform() -> str:
    """The FMI 2.0 platform folder for this machine (only linux64 is supported)."""
    if sys.platform.startswith("linux") and platform.machine() in ("x86_64", "AMD64"):
        return PLATFORM
    raise FmuBuilderError(f"unsupported platform {sys.platform}/{platform.machine()}: fmubuilder runs FMUs on linux x86_64 only")


def read_model_info(path: str | Path) -> ModelInfo:
    """Read and check the modelDescription of an FMU without extracting its binaries."""
    path = Path(path)
    if not path.exists():
        raise FmuBuilderError(f"{path}: no such file; give the path of an .fmu file")
    if path.is_dir():
        raise FmuBuilderError(f"{path} is a directory; give the path of an .fmu file (a zip archive)")
    if not zipfile.is_zipfile(path):
        raise FmuBuilderError(f"{path} is not an FMU (not a zip archive); export the model as an FMI 2.0 FMU")
    with zipfile.ZipFile(path) as zf:
        names = set(zf.namelist())
    if "modelDescription.xml" not in names:
        raise FmuBuilderError(f"{path} has no modelDescription.xml at its top level; it is not a valid FMU")
    _check_version(path)
    md = _parse_model_description(path)
    _check_kind(path, md)
    binary = f"binaries/{binary_platform()}/{md.modelExchange.modelIdentifier}.so"
    if binary not in names:
        platforms = sorted({n.split("/")[1] for n in names if n.startswith("binaries/") and n.count("/") >= 2})
        found = f"it has binaries for {', '.join(platforms)}" if platforms else "it has no binaries"
        raise FmuBuilderError(
            f"{path} has no {binary_platform()} binary ({binary}); {found}: re-export it for Linux x86_64")
    return model_info_from_fmpy(md)


def _parse_model_description(path: Path):
    from fmpy import read_model_description
    try:
        return read_model_description(str(path), validate=False)
    except Exception as exc:  # lxml and fmpy raise many kinds; the message is what matters
        first_line = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise FmuBuilderError(f"{path}: cannot read modelDescription.xml ({first_line})") from None


def _check_version(path: Path) -> None:
    """Check fmiVersion from the root element alone: other versions' XML may not parse as 2.0."""
    import xml.etree.ElementTree as ET
    try:
        with zipfile.ZipFile(path) as zf, zf.open("modelDescription.xml") as xml:
            _, root = next(ET.iterparse(xml, events=("start",)))
    except (ET.ParseError, StopIteration) as exc:
        raise FmuBuilderError(f"{path}: cannot read modelDescription.xml ({exc})") from None
    version = root.get("fmiVersion", "unknown")
    if not version.startswith("2."):
        raise FmuBuilderError(
            f"{path} is an FMI {version} FMU; fmubuilder needs FMI 2.0 (re-export the model for FMI 2.0)")


def _check_kind(path: Path, md) -> None:
    if md.modelExchange is None:
        raise FmuBuilderError(
            f"{path} supports Co-Simulation only; fmubuilder needs Model Exchange (re-export it with Model Exchange enabled)")


class FmuArchive:
    """An FMU extracted to a private temporary folder, removed on close() or at exit."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.info = read_model_info(self.path)
        self.directory = Path(tempfile.mkdtemp(prefix=f"fmubuilder-{self.info.model_identifier}-"))
        self._cleanup = weakref.finalize(self, shutil.rmtree, self.directory, True)
        try:
            with zipfile.ZipFile(self.path) as zf:
                _safe_extract(zf, self.directory)
        except (zipfile.BadZipFile, OSError) as exc:
            self._cleanup()
            raise FmuBuilderError(f"{self.path}: cannot extract the FMU ({exc})") from None

    @property
    def library_path(self) -> Path:
        return self.directory / "binaries" / binary_platform() / f"{self.info.model_identifier}.so"

    @property
    def resources_uri(self) -> str:
        return (self.directory / "resources").as_uri() + "/"

    def close(self) -> None:
        self._cleanup()


def _safe_extract(zf: zipfile.ZipFile, target: Path) -> None:
    """Extract, refusing entries that would land outside the target folder."""
    root = target.resolve()
    for member in zf.infolist():
        dest = (root / member.filename).resolve()
        if root != dest and root not in dest.parents:
            raise FmuBuilderError(f"FMU entry '{member.filename}' points outside the archive; the FMU is corrupt")
    zf.extractall(root)
