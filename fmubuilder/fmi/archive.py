"""Open an FMU file: check that it is an FMI 2.0 Model-Exchange FMU we can run, extract it.

Every way an FMU can be unusable ends here in one FmuBuilderError that names the problem
and what to do, so the stages behind this never see a half-valid FMU.
"""
from __future__ import annotations

import os
import platform
import shutil
import sys
import tempfile
import weakref
import zipfile
import zlib
from pathlib import Path

from ..errors import FmuBuilderError, first_line
from .model import ModelInfo, check_model_description, model_info_from_fmpy

PLATFORM = "linux64"
# FMI 2.0.4 / 3.0 build description: which sources to compile with which definitions.
BUILD_DESCRIPTION = "sources/buildDescription.xml"
# Extraction cap: an FMU's binary and resources rarely exceed a few hundred MB; a zip bomb does.
MAX_EXTRACT_ENV = "FMUBUILDER_MAX_EXTRACT_MB"
DEFAULT_MAX_EXTRACT_MB = 1024
_CORRUPT = (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError)


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
        raise FmuBuilderError(f"{path} is not an FMU (not a zip archive{_looks_truncated(path)}); "
                              "export the model as an FMI 2.0 FMU")
    try:
        with zipfile.ZipFile(path) as zf:
            names = set(zf.namelist())
    except _CORRUPT as exc:
        raise corrupt(path, exc) from None
    if "modelDescription.xml" not in names:
        raise FmuBuilderError(f"{path} has no modelDescription.xml at its top level; it is not a valid FMU")
    _check_version(path)
    md = _parse_model_description(path)
    _check_kind(path, md)
    check_model_description(md, path)
    binary = binary_entry(md.modelExchange.modelIdentifier)
    if binary not in names and not _ships_sources(names, md):
        platforms = binary_platforms(names)
        found = f"it has binaries for {', '.join(platforms)}" if platforms else "it has no binaries"
        raise FmuBuilderError(
            f"{path} has no {binary_platform()} binary ({binary}); {found} and no declared C sources: "
            "re-export it for Linux x86_64 or with its source code")
    return model_info_from_fmpy(md)


def binary_entry(model_identifier: str) -> str:
    """The archive entry of the FMU's shared library for this machine."""
    return f"binaries/{binary_platform()}/{model_identifier}.so"


def binary_platforms(names) -> list[str]:
    """The platform folders under binaries/ among an archive's entry names."""
    return sorted({n.split("/")[1] for n in names if n.startswith("binaries/") and n.count("/") >= 2} - {""})


def _ships_sources(names: set[str], md) -> bool:
    """Sources we can compile (fmi.sources): a build description or <SourceFiles> for Model Exchange."""
    if BUILD_DESCRIPTION in names:
        return True
    identifier = md.modelExchange.modelIdentifier
    for config in md.buildConfigurations:
        files = [f for s in config.sourceFileSets for f in s.sourceFiles]
        if config.modelIdentifier == identifier and files:
            return all(f"sources/{name}" in names for name in files)
    return False


def corrupt(path: Path, exc: BaseException, entry: str | None = None) -> FmuBuilderError:
    detail = first_line(exc)
    where = f" in {entry}" if entry and entry not in detail else ""
    return FmuBuilderError(f"{path} is corrupt ({detail}{where}): the archive is damaged or truncated; "
                           "copy or export the FMU again")


def _looks_truncated(path: Path) -> str:
    with open(path, "rb") as file:
        return ": it starts like one, so it is probably truncated or damaged" if file.read(2) == b"PK" else ""


def _parse_model_description(path: Path):
    from fmpy import read_model_description
    try:
        return read_model_description(str(path), validate=False)
    except _CORRUPT as exc:
        raise corrupt(path, exc, "modelDescription.xml") from None
    except Exception as exc:  # lxml and fmpy raise many kinds; the message is what matters
        raise FmuBuilderError(f"{path}: cannot read modelDescription.xml ({first_line(exc)})") from None


def _check_version(path: Path) -> None:
    """Check fmiVersion from the root element alone: other versions' XML may not parse as 2.0."""
    import xml.etree.ElementTree as ET
    try:
        with zipfile.ZipFile(path) as zf, zf.open("modelDescription.xml") as xml:
            _, root = next(ET.iterparse(xml, events=("start",)))
    except (ET.ParseError, StopIteration, LookupError, ValueError) as exc:   # LookupError: unknown encoding
        raise FmuBuilderError(f"{path}: cannot read modelDescription.xml ({first_line(exc)}); "
                              "re-export the model (FMI 2.0 model descriptions are UTF-8)") from None
    except _CORRUPT as exc:
        raise corrupt(path, exc, "modelDescription.xml") from None
    version = root.get("fmiVersion", "unknown")
    if not version.startswith("2."):
        raise FmuBuilderError(
            f"{path} is an FMI {version} FMU; fmubuilder needs FMI 2.0 (re-export the model for FMI 2.0)")


def _check_kind(path: Path, md) -> None:
    if md.modelExchange is None:
        raise FmuBuilderError(
            f"{path} supports Co-Simulation only; fmubuilder needs Model Exchange (re-export it with Model Exchange enabled)")


class FmuArchive:
    """An FMU extracted to a private temporary folder, removed on close() or at exit.

    ``runnable`` is the file to extract when it differs from ``path``: the copy of a source FMU
    with a compiled binary (fmi.sources.runnable_fmu).
    """

    def __init__(self, path: str | Path, runnable: str | Path | None = None):
        self.path = Path(path)
        self.info = read_model_info(self.path)
        self.directory = Path(tempfile.mkdtemp(prefix=f"fmubuilder-{self.info.model_identifier}-"))
        self._cleanup = weakref.finalize(self, shutil.rmtree, self.directory, True)
        try:
            with zipfile.ZipFile(runnable or self.path) as zf:
                _extract_needed(zf, self.directory, self.path, self.info.model_identifier)
        except FmuBuilderError:
            self._cleanup()
            raise
        except OSError as exc:
            self._cleanup()
            raise FmuBuilderError(f"{self.path}: cannot extract the FMU to {self.directory.parent} "
                                  f"({exc.strerror or exc}); free some space or set TMPDIR to another folder") from None

    @property
    def library_path(self) -> Path:
        return self.directory / binary_entry(self.info.model_identifier)

    @property
    def resources_uri(self) -> str:
        return (self.directory / "resources").as_uri() + "/"

    def close(self) -> None:
        self._cleanup()


def max_extract_bytes() -> int:
    text = os.environ.get(MAX_EXTRACT_ENV, "")
    try:
        megabytes = float(text) if text else DEFAULT_MAX_EXTRACT_MB
    except ValueError:
        raise FmuBuilderError(f"{MAX_EXTRACT_ENV}={text!r}: give a number of megabytes, e.g. 4096") from None
    return int(megabytes * 1024 * 1024)


def check_archive(path: str | Path) -> None:
    """Check what running the FMU needs without extracting it: entries stay inside the archive,
    sizes stay under the cap, the data inflate and match their CRCs."""
    path = Path(path)
    with zipfile.ZipFile(path) as zf:
        budget = [max_extract_bytes()]
        for member in _needed_members(zf, path, Path("/nonexistent/fmu")):
            if not member.is_dir():
                inflate_member(zf, member, path, lambda block: None, budget)


def _extract_needed(zf: zipfile.ZipFile, target: Path, path: Path, model_identifier: str) -> None:
    """Extract what running the FMU needs (modelDescription.xml, the linux64 binaries, resources/)."""
    root = target.resolve()
    budget = [max_extract_bytes()]
    for member in _needed_members(zf, path, root):
        dest = root / member.filename
        if member.is_dir():
            dest.mkdir(parents=True, exist_ok=True)
            continue
        dest.parent.mkdir(parents=True, exist_ok=True)
        with open(dest, "wb") as out:
            inflate_member(zf, member, path, out.write, budget)
        if member.external_attr >> 16 & 0o111:
            dest.chmod(0o755)


def _needed_members(zf: zipfile.ZipFile, path: Path, root: Path) -> list[zipfile.ZipInfo]:
    """The entries running the FMU needs, refusing entries that would land outside the
    extraction folder and archives whose declared sizes break the cap."""
    wanted = ("modelDescription.xml", f"binaries/{binary_platform()}/", "resources/")
    members = [m for m in zf.infolist() if m.filename.startswith(wanted)]
    for member in members:
        check_entry_inside(path, root, member.filename)
    budget, declared = max_extract_bytes(), 0
    for member in members:
        declared += member.file_size
        if declared > budget or (member.file_size > 2**26 and member.file_size > 1000 * member.compress_size):
            raise _too_large(path, member, declared > budget)
    return members


def check_entry_inside(path: Path, root: Path, name: str) -> Path:
    """Where entry ``name`` lands under ``root``; refuses names that leave it (``..``, absolute)."""
    root = root.resolve()
    dest = (root / name).resolve()
    if root != dest and root not in dest.parents:
        raise FmuBuilderError(f"{path}: entry '{name}' points outside the archive; the FMU is corrupt "
                              "or malicious: do not use it")
    return dest


def inflate_member(zf: zipfile.ZipFile, member: zipfile.ZipInfo, path: Path, write, budget: list[int]) -> None:
    """Inflate one entry into `write`, counting the bytes actually produced against the
    archive's budget (one-element list, shared by its entries): headers can lie."""
    try:
        with zf.open(member) as source:
            while block := source.read(1 << 20):
                budget[0] -= len(block)
                if budget[0] < 0:
                    raise _too_large(path, member, True)
                write(block)
    except _CORRUPT as exc:
        raise corrupt(path, exc, member.filename) from None


def _too_large(path: Path, member: zipfile.ZipInfo, over_limit: bool) -> FmuBuilderError:
    size = f"{member.file_size / 2**20:.0f} MB"
    if over_limit:
        problem = f"would extract to more than {max_extract_bytes() / 2**20:g} MB ({member.filename}: {size})"
    else:
        problem = f"has {member.filename} compressed {member.file_size / max(member.compress_size, 1):.0f}:1 ({size})"
    return FmuBuilderError(f"{path} {problem}, which looks like a zip bomb; if the FMU is genuine, raise the limit "
                           f"with {MAX_EXTRACT_ENV}=<megabytes>")
