"""What a command will write and read, checked before it does any work.

Every command declares its plan (`Plan`): the output files it writes, the folders it stages and
swaps in (a report, the demo), the folders it writes named files into (plots) and the files it
reads. `check` runs before the command's function, so that every refusal comes in the first
second and nothing the user had is touched:

* an output is a regular file or nothing (never a folder, device, FIFO or symbolic link), it
  exists only with --force, its folder exists and takes a new file (probed), and it is not an
  input, nor inside a folder output;
* a folder output is a folder or nothing; an existing one is replaced only with --force and only
  when fmubuilder made it (its manifest, files unchanged: files.refuse_foreign_folder); no input
  lies inside it;
* no two outputs are one path.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import FmuBuilderError
from ..files import (check_writable_folder, inside, kind_of, refuse_foreign_folder, refuse_non_regular,
                     same_file)


@dataclass
class Plan:
    force: bool = False
    files: list[tuple[str, str]] = field(default_factory=list)      # (option, path)
    folders: list[tuple[str, str]] = field(default_factory=list)    # (option, path): staged, swapped in
    into: list[tuple[str, str, tuple[str, ...]]] = field(default_factory=list)  # (option, folder, file names)
    inputs: list[str] = field(default_factory=list)

    def paths(self) -> list[Path]:
        """Every output path, for the supervisor's note of what a failed run changed."""
        return ([Path(p) for _, p in self.files] + [Path(p) for _, p in self.folders]
                + [Path(folder) / name for _, folder, names in self.into for name in names])


def inputs_with_sidecars(*paths) -> list[str]:
    """The given input paths (None left out), each data CSV with its `<csv>.json` sidecar."""
    found = []
    for path in paths:
        if path is None:
            continue
        found.append(str(path))
        if str(path).lower().endswith(".csv"):
            found.append(f"{path}.json")
    return found


def check(plan: Plan) -> None:
    inputs = [p for p in plan.inputs if p and os.path.lexists(p)]
    outputs: list[tuple[str, str]] = []
    for option, path in plan.files:
        _check_file(option, path, plan.force, inputs)
        outputs.append((option, path))
    for option, folder in plan.folders:
        for other_option, other in outputs:
            if os.path.abspath(other) == os.path.abspath(folder):
                raise FmuBuilderError(f"{other_option} and {option} are the same path ({folder}); give each "
                                      "output its own path")
        _check_folder(option, folder, plan.force, inputs)
        for other_option, other in outputs:
            if inside(other, folder):
                raise FmuBuilderError(f"{other_option} {other} lies in the folder {option} {folder}, which is "
                                      "replaced as a whole; choose paths apart")
        outputs.append((option, folder))
    for option, folder, names in plan.into:
        if kind_of(folder) not in (None, "folder") and not os.path.isdir(folder):
            raise FmuBuilderError(f"{option} {folder} is a {kind_of(folder)}, not a folder; choose a folder")
        for name in names:
            _check_file(option, str(Path(folder) / name), plan.force, inputs, probe=False)
            outputs.append((option, str(Path(folder) / name)))
        _probe_nearest(folder, option)
    for i, (option, path) in enumerate(outputs):
        for other_option, other in outputs[:i]:
            if os.path.abspath(path) == os.path.abspath(other) or (os.path.lexists(path) and same_file(path, other)):
                raise FmuBuilderError(f"{other_option} and {option} are the same path ({path}); give each "
                                      "output its own path")


def _check_file(option: str, path: str, force: bool, inputs: list[str], probe: bool = True) -> None:
    try:
        refuse_non_regular(path)
    except FmuBuilderError:
        raise FmuBuilderError(f"{option} {path} is a {kind_of(path)}, not a regular file; fmubuilder writes only "
                              "regular files: give the path of a new or regular file") from None
    for source in inputs:
        if same_file(path, source):
            raise FmuBuilderError(f"{option} {path} is an input of this command ({source}); "
                                  "give the output another path")
    if os.path.lexists(path) and not force:
        raise FmuBuilderError(f"{path} exists; choose another output path or pass --force to overwrite it")
    folder = Path(path).parent
    if probe:
        if not folder.is_dir():
            raise FmuBuilderError(f"cannot write {path}: folder {folder} does not exist; create it first")
        check_writable_folder(folder, path)


def _check_folder(option: str, folder: str, force: bool, inputs: list[str]) -> None:
    kind = kind_of(folder)
    if kind not in (None, "folder"):
        raise FmuBuilderError(f"{option} {folder} is a {kind}, not a folder; choose a folder path")
    for source in inputs:
        if inside(source, folder):
            raise FmuBuilderError(f"{option} {folder} holds the input {source}; the folder is replaced as a whole: "
                                  "choose a new folder for the output")
    if kind == "folder" and any(Path(folder).iterdir()):
        if not force:
            raise FmuBuilderError(f"{option} {folder} exists and is not empty; choose another folder or pass "
                                  "--force to replace a folder fmubuilder wrote")
        refuse_foreign_folder(folder, f"{option} folder")
    _probe_nearest(str(Path(folder).parent), option)   # staged beside it, then swapped in


def _probe_nearest(folder: str, option: str) -> None:
    """The folder, or its nearest existing parent (the folder is created), must take a new file."""
    nearest = Path(os.path.abspath(folder))
    while not nearest.exists():
        nearest = nearest.parent
    if not nearest.is_dir():
        raise FmuBuilderError(f"cannot create {option} {folder}: {nearest} is a {kind_of(nearest)}, not a folder")
    check_writable_folder(nearest, folder)
