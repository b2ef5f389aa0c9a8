"""`fmubuilder demo`: the main job on the bundled example, end to end.

Writes the VLDM example (declared FMU, truth FMUs, measured data sets), then runs
`hybridize` on the extra-resistance data: diagnosis, fitted term and NeuralFMU, the choice on
the validation part of the training run (its last 20 %), the test cycle scored once after it,
round-trip validation, report. The work is counted in epochs, so the numbers do not depend on
how busy the machine is.
"""
from __future__ import annotations

import shutil
from pathlib import Path

from .errors import FmuBuilderError

CASE = "extra_resistance"


def run_demo(output: Path, force: bool = False, time_budget: float | None = None, epochs: int | None = None):
    """Write the example and hybridize it; returns the HybridizeResult and the example folder."""
    from .examples_zoo import write_example
    from .hybridize.workflow import DEFAULT_EPOCHS, hybridize

    out = _prepare_output_dir(Path(output), force)
    example = out / "example"
    print(f"writing the VLDM example (FMUs and measured data) to {example}/ ...")
    write_example("vldm", example)
    result = hybridize(example / "vldm.fmu", example / f"{CASE}_train_cadc.csv", example / f"{CASE}_test_wltc2.csv",
                       out / "vldm_hybrid.fmu", out / "report", time_budget=time_budget,
                       epochs=DEFAULT_EPOCHS if epochs is None else epochs)
    return result, example


def _prepare_output_dir(path: Path, force: bool) -> Path:
    if path.exists():
        if not force:
            raise FmuBuilderError(f"{path} exists; choose another folder with -o or pass --force to replace it")
        shutil.rmtree(path)
    path.mkdir(parents=True)
    return path
