"""Writing outputs safely: every stage writes through these helpers.

A file is written next to its target under a hidden `.NAME.XXXX.partial` name and renamed
into place, so a reader (or a crash half-way) never sees a half-written file. A folder is staged
beside its target and swapped in when complete; it carries a manifest (`MANIFEST_NAME`) of the
files fmubuilder wrote into it, and `--force` replaces only such a folder, unchanged.

Nothing else is ever removed: a run records every path it creates (its staged files and folders,
and the outputs it created where nothing was before) in a journal (`JOURNAL_ENV`, set by the
command line's supervisor), and the clean-up of a failed run removes exactly those paths, each
only while it is still the file this run made (same device and inode), never what another
process created or what the user had.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import stat
import tempfile
from pathlib import Path

from .errors import FmuBuilderError

PARTIAL_SUFFIX = ".partial"
MANIFEST_NAME = ".fmubuilder-manifest.json"
MANIFEST_FORMAT = "fmubuilder-folder/1"
JOURNAL_ENV = "FMUBUILDER_JOURNAL"


# -- what a path is --------------------------------------------------------------------------

def kind_of(path: str | os.PathLike) -> str | None:
    """None when nothing is at `path`, else 'file', 'folder', 'symbolic link', 'device', 'FIFO',
    'socket' (the path itself, a link not followed)."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise FmuBuilderError(f"cannot use {path}: {exc.strerror or exc}") from None
    if stat.S_ISREG(mode):
        return "file"
    if stat.S_ISDIR(mode):
        return "folder"
    if stat.S_ISLNK(mode):
        return "symbolic link"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "device"
    if stat.S_ISFIFO(mode):
        return "FIFO"
    return "socket"


def refuse_non_regular(path: str | os.PathLike) -> None:
    """An error when something other than a regular file (or nothing) is at `path`: fmubuilder
    replaces only regular files, never a folder, device, FIFO or a symbolic link."""
    kind = kind_of(path)
    if kind not in (None, "file"):
        raise FmuBuilderError(f"{path} is a {kind}, not a regular file; fmubuilder replaces only regular files: "
                              "give the path of a new or regular file")


def refuse_existing(path: str | os.PathLike, force: bool) -> Path:
    """`path` as a Path; an error if it exists and `force` does not allow overwriting it, or if it is
    not a regular file (a folder, device, FIFO or symbolic link, never replaced)."""
    path = Path(path)
    refuse_non_regular(path)
    if path.exists() and not force:
        raise FmuBuilderError(f"{path} exists; choose another output path or pass --force to overwrite it")
    return path


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Whether two paths name the same file (after links, `..`, hard links)."""
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def inside(path: str | os.PathLike, folder: str | os.PathLike) -> bool:
    """Whether `path` (resolved) is `folder` or lies under it."""
    path, folder = os.path.realpath(path), os.path.realpath(folder)
    return path == folder or path.startswith(folder.rstrip(os.sep) + os.sep)


def check_writable_folder(folder: str | os.PathLike, target: str | os.PathLike) -> None:
    """An error unless a file can be created in `folder` (probed with a staged file, removed at once):
    a read-only mount, /proc or a folder without write permission is found before any work."""
    try:
        fd, probe = tempfile.mkstemp(dir=folder, prefix=f".{Path(target).name}.", suffix=PARTIAL_SUFFIX)
    except OSError as exc:
        raise FmuBuilderError(f"cannot write {target}: {exc.strerror or exc} (in {folder}); "
                              "choose an output path in a folder you can write to") from None
    os.close(fd)
    os.unlink(probe)


# -- the journal of what this run created ------------------------------------------------------

_created_here: set[str] = set()     # the outputs this process created, replaced again by it later


def _record(kind: str, path: Path) -> None:
    """Note in the journal that this run made `path`: "staged" (a hidden .partial file or folder of
    a unique name), "created" (an output where nothing was before) or "folder" (made to hold outputs)."""
    journal = os.environ.get(JOURNAL_ENV)
    if not journal:
        return
    try:
        info = os.lstat(path)
        with open(journal, "a", encoding="utf-8") as handle:
            handle.write(json.dumps([kind, os.path.abspath(path), info.st_dev, info.st_ino, info.st_ctime_ns]) + "\n")
    except OSError:
        pass
    if kind == "created":
        _created_here.add(os.path.abspath(path))


@contextlib.contextmanager
def kept_on_failure():
    """Paths created inside the block are not journaled: they stay when the run fails later (a batch
    keeps each case it completed, and its summary, when a later case or an interrupt ends it)."""
    journal = os.environ.pop(JOURNAL_ENV, None)
    try:
        yield
    finally:
        if journal is not None:
            os.environ[JOURNAL_ENV] = journal


def created_paths(journal: str | os.PathLike) -> list[tuple[str, Path]]:
    """(kind, path) of the paths a run recorded in `journal` that are still the ones it made, newest
    first: what the clean-up of a failed run may remove. The same device and inode; for a created
    file also its status-change time (an inode number is reused: a file another program wrote there
    since has its own). A staged path has a unique random name, and a folder fills after it was made."""
    try:
        lines = Path(journal).read_text(encoding="utf-8").splitlines()
    except OSError:
        return []
    found, seen = [], set()
    for line in reversed(lines):
        try:
            kind, path, device, inode, changed = json.loads(line)
            info = os.lstat(path)
        except (ValueError, TypeError, OSError):
            continue
        same = (info.st_dev, info.st_ino) == (device, inode)
        if kind == "created" and stat.S_ISREG(info.st_mode):
            same = same and info.st_ctime_ns == changed
        if same and path not in seen:
            seen.add(path)
            found.append((kind, Path(path)))
    return found


def keep_for_the_user(path: str | os.PathLike) -> Path:
    """Mark an output of a run that then fails as one its error message points to: the clean-up of
    the failed run leaves it (and what lies in it). Returns `path`."""
    _record("kept", Path(path))
    return Path(path)


def remove_created(journal: str | os.PathLike) -> list[Path]:
    """Remove what a failed run created (`created_paths`), except what it kept for the user
    (`keep_for_the_user`); returns the paths removed. A staged or published folder goes with its
    content (all the run's); a folder `make_folder` made only when it is empty by then: files
    another program put there stay."""
    removed = []
    created = created_paths(journal)
    kept = [path for kind, path in created if kind == "kept"]
    for kind, path in created:
        if kind == "kept" or any(path == k or k in path.parents for k in kept):
            continue
        if kind == "folder":
            with contextlib.suppress(OSError):
                os.rmdir(path)
        elif os.path.isdir(path) and not os.path.islink(path):
            shutil.rmtree(path, ignore_errors=True)
        else:
            with contextlib.suppress(OSError):
                os.unlink(path)
        if not os.path.lexists(path):
            removed.append(path)
    return removed


def make_folder(path: str | os.PathLike) -> Path:
    """Create the folder `path` (and missing parents), recording the ones this run created."""
    path = Path(path)
    missing = []
    for folder in (path, *path.parents):
        if os.path.lexists(folder):
            break
        missing.append(folder)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise FmuBuilderError(f"cannot create the folder {path}: {exc.strerror or exc}") from None
    for folder in reversed(missing):
        _record("folder", folder)
    return path


# -- atomic files ------------------------------------------------------------------------------

def write_atomically(target: str | os.PathLike, data: bytes | str) -> Path:
    """Write `data` (text as UTF-8) to `target` atomically."""
    payload = data.encode("utf-8") if isinstance(data, str) else data
    return _replace_atomically(Path(target), lambda handle: handle.write(payload))


def copy_atomically(source: str | os.PathLike, target: str | os.PathLike) -> Path:
    """Copy the file `source` to `target` atomically."""
    if os.path.lexists(target) and same_file(source, target):
        raise FmuBuilderError(f"cannot copy {source} onto itself ({target}); give another output path")

    def copy(handle):
        with open(source, "rb") as original:
            shutil.copyfileobj(original, handle, 1 << 20)
    return _replace_atomically(Path(target), copy)


def _replace_atomically(target: Path, write) -> Path:
    folder = target.parent      # Path("x").parent is Path(".")
    if not folder.is_dir():
        raise FmuBuilderError(f"cannot write {target}: folder {folder} does not exist; create it first")
    if target.is_dir() and not target.is_symlink():
        raise FmuBuilderError(f"cannot write {target}: it is a folder; give a file name")
    refuse_non_regular(target)
    try:
        fd, temporary = tempfile.mkstemp(dir=folder, prefix=f".{target.name}.", suffix=PARTIAL_SUFFIX)
    except OSError as exc:
        raise FmuBuilderError(f"cannot write {target}: {exc.strerror or exc}") from None
    _record("staged", Path(temporary))
    try:
        os.fchmod(fd, 0o644)  # mkstemp creates 0600; give the file the permissions of a new file
        with os.fdopen(fd, "wb") as handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())
        refuse_non_regular(target)      # again: something may have appeared there meanwhile
        existed = os.path.lexists(target)
        os.replace(temporary, target)
    except OSError as exc:
        Path(temporary).unlink(missing_ok=True)
        raise FmuBuilderError(f"cannot write {target}: {exc.strerror or exc}") from None
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    if not existed or os.path.abspath(target) in _created_here:
        _record("created", target)
    return target


# -- folders: staged, marked, swapped ---------------------------------------------------------

def staging_folder(target: str | os.PathLike) -> Path:
    """An empty folder beside `target` (hidden, `.partial`) to build a new version of it in;
    `replace_folder` then puts it in target's place. Same file system, so the swap is a rename."""
    target = Path(target)
    try:
        make_folder(target.parent)
        staging = Path(tempfile.mkdtemp(dir=target.parent, prefix=f".{target.name}.", suffix=PARTIAL_SUFFIX))
    except OSError as exc:
        raise FmuBuilderError(f"cannot write {target}: {exc.strerror or exc}") from None
    _record("staged", staging)
    return staging


def write_manifest(folder: str | os.PathLike) -> Path:
    """Mark `folder` as fmubuilder's: a manifest of every file in it (relative path and SHA-256)."""
    folder = Path(folder)
    files, folders = _contents(folder)
    manifest = {"format": MANIFEST_FORMAT, "folders": folders,
                "files": {name: file_sha256(folder / name) for name in files}}
    return write_atomically(folder / MANIFEST_NAME, json.dumps(manifest, indent=1, sort_keys=True) + "\n")


def _contents(folder: Path) -> tuple[list[str], list[str]]:
    """(files, folders) under `folder` as relative POSIX paths, the manifest left out; a symbolic
    link, device or FIFO inside counts as a file (and is never one fmubuilder wrote)."""
    files, folders = [], []
    for root, dirs, names in os.walk(folder):
        base = Path(root)
        for name in dirs:
            if (base / name).is_symlink():
                files.append((base / name).relative_to(folder).as_posix())
        dirs[:] = [d for d in dirs if not (base / d).is_symlink()]
        folders += [(base / d).relative_to(folder).as_posix() for d in dirs]
        files += [(base / n).relative_to(folder).as_posix() for n in names]
    files = [f for f in files if f != MANIFEST_NAME]
    return sorted(files), sorted(folders)


def foreign_content(folder: str | os.PathLike) -> str | None:
    """None when `folder` is empty or holds exactly what fmubuilder wrote into it (its manifest,
    the files unchanged); else what is not fmubuilder's, for the error message."""
    folder = Path(folder)
    files, folders = _contents(folder)
    if not files and not folders and not (folder / MANIFEST_NAME).exists():
        return None
    try:
        manifest = json.loads((folder / MANIFEST_NAME).read_text(encoding="utf-8"))
        listed, listed_folders = dict(manifest["files"]), set(manifest["folders"])
    except (OSError, ValueError, KeyError, TypeError):
        first = (files or folders)[0] if files or folders else MANIFEST_NAME
        return f"it holds '{first}' and no fmubuilder manifest, so fmubuilder did not write it"
    for name in files:
        if name not in listed:
            return f"it holds '{name}', which fmubuilder did not write"
        if kind_of(folder / name) != "file" or file_sha256(folder / name) != listed[name]:
            return f"'{name}' changed since fmubuilder wrote it"
    for name in folders:
        if name not in listed_folders:
            return f"it holds the folder '{name}', which fmubuilder did not write"
    return None


def refuse_foreign_folder(folder: str | os.PathLike, what: str = "folder") -> None:
    """An error unless `folder` may be replaced: nothing there, or a folder fmubuilder made, unchanged."""
    kind = kind_of(folder)
    if kind is None:
        return
    if kind != "folder":
        raise FmuBuilderError(f"the {what} {folder} is a {kind}, not a folder; choose a folder path")
    reason = foreign_content(folder)
    if reason:
        raise FmuBuilderError(f"will not replace the {what} {folder}: {reason}; --force replaces only a folder "
                              "fmubuilder made: choose a new folder or move its files away")


def replace_folder(staging: str | os.PathLike, target: str | os.PathLike) -> Path:
    """Put the complete folder `staging` in target's place, marked with a manifest; an old `target`
    is replaced only when fmubuilder made it (`refuse_foreign_folder`), and removed only after the
    new one is in place (two renames: a reader sees the old or the new folder, never a mix)."""
    staging, target = Path(staging), Path(target)
    if os.path.lexists(target) and kind_of(target) != "folder":
        raise FmuBuilderError(f"cannot write the folder {target}: a {kind_of(target)} has that name; "
                              "remove it or choose another")
    refuse_foreign_folder(target)
    write_manifest(staging)
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
    else:
        _record("created", target)
    return target


def partial_files(target: str | os.PathLike) -> list[Path]:
    """Leftovers of an interrupted atomic write of `target` (by their name: they may be another
    run's; the clean-up removes only the paths its own journal lists)."""
    target = Path(target)
    return sorted(target.parent.glob(f".{target.name}.*{PARTIAL_SUFFIX}")) if target.parent.is_dir() else []


def file_sha256(path: str | os.PathLike) -> str:
    with open(path, "rb") as handle:
        return hashlib.file_digest(handle, "sha256").hexdigest()
