"""The crashing bouncing-ball FMUs (tests/fmi/crashing), built once and cached like the examples."""
from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
from pathlib import Path

from fmubuilder.build import build_cmake_project, cache_dir, repo_root

HERE = Path(__file__).resolve().parent / "crashing"
MODES = ("segfault", "abort", "exit0", "exit3", "hang", "instantiate_segfault")


def crash_fmus() -> dict[str, Path]:
    """{mode: FMU path}; every FMU has the bouncing ball's modelDescription and GUID."""
    root = repo_root()
    inputs = [HERE / "crash_model.c", HERE / "CMakeLists.txt", root / "cmake" / "fmu.cmake",
              root / "examples" / "common" / "fmi2_glue.c", root / "examples" / "common" / "model.h",
              *sorted((root / "examples" / "bouncing_ball").iterdir())]
    digest = hashlib.sha256()
    for path in inputs:
        digest.update(path.name.encode() + b"\0" + path.read_bytes())
    final = cache_dir() / "test_fmus" / f"crashing-{digest.hexdigest()[:16]}"
    if not final.is_dir():
        final.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(prefix=".crashing-", dir=final.parent) as scratch:
            build = build_cmake_project(HERE, Path(scratch) / "build")
            staged = Path(scratch) / "fmus"
            staged.mkdir()
            for fmu in build.fmus():
                shutil.copy2(fmu, staged / fmu.name)
            try:
                os.rename(staged, final)
            except OSError:
                if not final.is_dir():  # not another process finishing first
                    raise
    return {mode: final / f"{mode}.fmu" for mode in MODES}
