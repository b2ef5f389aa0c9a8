"""Wall time and outcome of diagnose() on data from the example truth FMUs.

For each case the bench of fmubuilder.synth logs a truth FMU, then the declared model is
diagnosed over the whole window. Printed per case: the verdict, the traced channel and
leading input, the fitted term, the number of simulations and the wall time, also as a ratio
to one plain run of the declared model over the same window (the baseline, measured in the
same diagnosis).

    python benchmarks/bench_diagnose.py [--cases dc_drive,vldm] [--seed S]
"""
from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

from fmubuilder import synth
from fmubuilder.build import example_fmu
from fmubuilder.diagnose import diagnose

DC_DRIVE = dict(signals=("speed", "current", "power", "temperature"),
                noise_std={"speed": 0.1, "current": 0.02, "power": 1.0, "temperature": 0.02})
CASES = {
    "dc_drive": ("dc_drive", 15.0, DC_DRIVE, None,
                 ["dc_drive", "dc_drive_truth_windage", "dc_drive_truth_extra_heating"]),
    "vldm": ("vldm", 30.0, dict(signals=("speed", "power", "energy")), {"cycle": 1},
             ["vldm", "vldm_truth_extra_resistance", "vldm_truth_extra_loss"]),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default="dc_drive,vldm")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="bench_diagnose_"))
    print(f"{'truth':<32}{'verdict':<10}{'channel':<18}{'input':<14}{'sims':>5}{'wall [s]':>10}"
          f"{'x plain run':>13}  term")
    for case in args.cases.split(","):
        model, stop, bench, start, truths = CASES[case]
        for truth in truths:
            settings = synth.BenchSettings(seed=args.seed, **bench)
            data = folder / f"{truth}.csv"
            synth.write_measurement(synth.measure(example_fmu(truth), stop_time=stop, start_values=start,
                                                  settings=settings), data)
            started = time.perf_counter()
            d = diagnose(example_fmu(model), data, time_budget=math.inf)
            wall = time.perf_counter() - started
            ratio = wall / d.wall_time["nominal"]
            term = d.fitted_term["expression"] if d.fitted_term else "-"
            verdict = "effect" if d.significant else "none"
            print(f"{truth:<32}{verdict:<10}{d.channel or '-':<18}{(d.inputs or ['-'])[0]:<14}{d.simulations:>5}"
                  f"{wall:>10.1f}{ratio:>13.0f}  {term}")


if __name__ == "__main__":
    main()
