"""Where the Modelica Reference FMUs (https://github.com/modelica/Reference-FMUs, BSD) are: the
folder named by FMUBUILDER_REFERENCE_FMUS, else a `shared/fmus/reference/` folder beside the
checkout or an enclosing folder. Tests that use them skip visibly when neither is there."""
import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent
RELATIVE = Path("shared") / "fmus" / "reference"
ENVIRONMENT = "FMUBUILDER_REFERENCE_FMUS"
NOT_FOUND = (f"the Modelica Reference FMUs were not found: set {ENVIRONMENT} to a folder holding their "
             "FMUs (from a Reference-FMUs release) to run these tests")


def reference_dir() -> Path | None:
    named = os.environ.get(ENVIRONMENT)
    if named:
        return Path(named) if Path(named).is_dir() else None
    for folder in REPO_ROOT.parents:
        candidate = folder / RELATIVE
        if candidate.is_dir():
            return candidate
    return None


def reference_fmu(name: str) -> Path:
    """Path of the Reference FMU `name` (e.g. "Feedthrough"), or a visible skip."""
    folder = reference_dir()
    if folder is None:
        pytest.skip(NOT_FOUND)
    path = folder / f"{name}.fmu"
    if not path.is_file():
        pytest.skip(f"{path} is missing")
    return path
