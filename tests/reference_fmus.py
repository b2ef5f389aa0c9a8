"""Where the Modelica Reference FMUs are: `../shared/fmus/reference/` beside the repository (a
checkout nested deeper, e.g. a worktree, finds it beside an enclosing folder). Tests that use them
skip visibly when the folder is missing."""
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent
RELATIVE = Path("shared") / "fmus" / "reference"


def reference_dir() -> Path | None:
    for folder in REPO_ROOT.parents:
        candidate = folder / RELATIVE
        if candidate.is_dir():
            return candidate
    return None


def reference_fmu(name: str) -> Path:
    """Path of the Reference FMU `name` (e.g. "Feedthrough"), or a visible skip."""
    folder = reference_dir()
    if folder is None:
        pytest.skip(f"the Reference FMUs are not beside the repository (../{RELATIVE.as_posix()}/)")
    path = folder / f"{name}.fmu"
    if not path.is_file():
        pytest.skip(f"{path} is missing")
    return path
