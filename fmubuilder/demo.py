"""`fmubuilder demo`: the VLDM example written, then `hybridize` on its extra-resistance data
(the README's "Set-up" and "The bundled example")."""
from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path

from .errors import FmuBuilderError

CASE = "extra_resistance"
# The demo's NeuralFMU training, in loss evaluations (each a simulation of all training elements with
# its gradient). The training integrates with the checked scoring's RK4 (h = 0.01 s on the VLDM), 1.9
# times the CPU time per evaluation of the explicit Euler at the same step it used before (2 epochs on
# the first 300 s of the CADC run, 50 s elements: 56 s against 30 s); 5 evaluations (the 5 Adam epochs
# of one step each it trained before) keep the demo's training time: an evaluation costs the same
# with L-BFGS (the DC drive's Stribeck NeuralFMU, 10 evaluations each, run side by side: 287 s wall
# against Adam's 290 s), which takes fewer steps and so fewer validation scorings of the ANN on the term.
DEMO_BUDGET = 5


def run_demo(output: Path, force: bool = False, time_budget: float | None = None, budget: int | None = None):
    """Write the example and hybridize it; returns the HybridizeResult and the example folder.
    With `force`, an earlier demo folder is replaced only when the new run succeeds."""
    from .examples_zoo import write_example
    from .hybridize import workflow

    with _replacing_folder(Path(output), force) as out:
        example = out / "example"
        print(f"writing the VLDM example (FMUs and measured data) to {example}/ ...")
        write_example("vldm", example)
        result = workflow.hybridize(
            example / "vldm.fmu", example / f"{CASE}_train_cadc.csv", example / f"{CASE}_test_wltc2.csv",
            out / "vldm_hybrid.fmu", out / "report", time_budget=time_budget,
            budget=DEMO_BUDGET if budget is None else budget)
    return result, example


@contextlib.contextmanager
def _replacing_folder(path: Path, force: bool):
    """The demo writes into `path` itself, because its report names the files it wrote there. An
    earlier demo folder is moved aside beside it (`NAME.previous-XXXX/`) for the run, removed when
    the run succeeds and put back when it fails."""
    if path.exists() and not path.is_dir():
        raise FmuBuilderError(f"{path} is a file; choose a folder for the demo with -o")
    if path.exists() and not force:
        raise FmuBuilderError(f"{path} exists; choose another folder with -o or pass --force to replace it "
                              "(the old one is kept until the new run succeeds)")
    aside = None
    if path.exists():
        aside = Path(tempfile.mkdtemp(dir=path.parent, prefix=f"{path.name}.previous-"))
        os.replace(path, aside / path.name)
    try:
        path.mkdir(parents=True)
        yield path
    except BaseException:
        shutil.rmtree(path, ignore_errors=True)
        if aside is not None:
            os.replace(aside / path.name, path)
            aside.rmdir()
        raise
    if aside is not None:
        shutil.rmtree(aside, ignore_errors=True)
