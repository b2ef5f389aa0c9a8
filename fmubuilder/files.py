"""Writing outputs safely: every stage writes through these helpers.

A file is written next to its target under a hidden `.NAME.XXXX.partial` name and renamed
into place, so a reader (or a crash half-way) never sees a half-written file. The CLI
removes such leftovers of a killed run by that pattern (`partial_files`).
"""
from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
from pathlib import Path

from .errors import FmuBuilderError

PARTIAL_SUFFIX = ".partial"


def refuse_existing(path: str | os.PathLike, force: bool) -> Path:
    """`path` as a Path; an error if it exists and `force` does not allow overwriting it."""
    path = Path(path)
    if path.exists() and not force:
        raise FmuBuilderError(f"{path} exists; choose another output path or pass --force to overwrite it")
    return path


def write_atomically(target: str | os.PathLike, data: bytes | str) -> Path:
    """Write `data` (text as UTF-8) to `target` atomically."""
    payload = data.encode("utf-8") if isinstance(data, str) else data
    return _replace_atomically(Path(target), lambda handle: handle.write(payload))


def copy_atomically(source: str | os.PathLike, target: str | os.PathLike) -> Path:
    """Copy the file `source` to `target` atomically."""
    def copy(handle):
        with open(source, "rb") as original:
            shutil.copyfileobj(original, handle, 1 << 20)
    return _replace_atomically(Path(target), copy)


def _replace_atomically(target: Path, write) -> Path:
    folder = target.parent      # Path("x").parent is Path(".")
    if not folder.is_dir():
        raise FmuBuilderError(f"cannot write {target}: folder {folder} does not exist; create it first")
    if target.is_dir():
        raise FmuBuilderError(f"cannot write {target}: it is a folder; give a file name")
    try:
        fd, temporary = tempfile.mkstemp(dir=folder, prefix=f".{target.name}.", suffix=PARTIAL_SUFFIX)
    except OSError as exc:
        raise FmuBuilderError(f"cannot write {target}: {exc.strerror or exc}") from None
    try:
        os.fchmod(fd, 0o644)  # mkstemp creates 0600; give the file the permissions of a new file
        with os.fdopen(fd, "wb") as handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, target)
    except OSError as exc:
        Path(temporary).unlink(missing_ok=True)
        raise FmuBuilderError(f"cannot write {target}: {exc.strerror or exc}") from None
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    return target


def staging_folder(target: str | os.PathLike) -> Path:
    """An empty folder beside `target` (hidden, `.partial`) to build a new version of it in;
    `replace_folder` then puts it in target's place. Same file system, so the swap is a rename."""
    target = Path(target)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        return Path(tempfile.mkdtemp(dir=target.parent, prefix=f".{target.name}.", suffix=PARTIAL_SUFFIX))
    except OSError as exc:
        raise FmuBuilderError(f"cannot write {target}: {exc.strerror or exc}") from None


def replace_folder(staging: str | os.PathLike, target: str | os.PathLike) -> Path:
    """Put the complete folder `staging` in target's place; an old `target` is removed only after
    the new one is in place (two renames: a reader sees the old or the new folder, never a mix)."""
    staging, target = Path(staging), Path(target)
    if target.exists() and not target.is_dir():
        raise FmuBuilderError(f"cannot write the folder {target}: a file has that name; remove it or choose another")
    old = None
    if target.exists():
        old = Path(tempfile.mkdtemp(dir=target.parent, prefix=f".{target.name}.", suffix=".old"))
        os.replace(target, old / "previous")
    try:
        os.replace(staging, target)
    except OSError as exc:
        if old is not None:     # the old folder back; should that fail, it stays in `old`, not lost
            os.replace(old / "previous", target)
            shutil.rmtree(old, ignore_errors=True)
        raise FmuBuilderError(f"cannot write {target}: {exc.strerror or exc}") from None
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    return target


def partial_files(target: str | os.PathLike) -> list[Path]:
    """Leftovers of an interrupted atomic write of `target`."""
    target = Path(target)
    return sorted(target.parent.glob(f".{target.name}.*{PARTIAL_SUFFIX}")) if target.parent.is_dir() else []


def file_sha256(path: str | os.PathLike) -> str:
    with open(path, "rb") as handle:
        return hashlib.file_digest(handle, "sha256").hexdigest()
