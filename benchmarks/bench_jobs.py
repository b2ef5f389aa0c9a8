"""The NeuralFMU trained in a second process beside the other candidates, against one process.

For each case (an example's truth variant, as in bench_effects.py) `hybridize` runs twice on the
same data and budget: `jobs=1` (every candidate one after the other, the baseline) and `jobs=2` (the
NeuralFMU in a forked helper while the fitted term, the calibrations and the ANN on the term are
built). Printed per case: the wall seconds of each and of their candidates stage, the ratio, and
whether the two report.json files hold the same numbers (they must: the work is the same).
Measure on an otherwise idle machine with two cores; the ratio is the point, not the seconds.

    python benchmarks/bench_jobs.py [--cases dc_drive:windage,vldm:extra_resistance] [--budget N]
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

from bench_effects import DECLARED, _cases, _data

from fmubuilder.build import example_fmu
from fmubuilder.fmi.side_process import can_run_beside, cores
from fmubuilder.hybridize import hybridize
from fmubuilder.hybridize.workflow import DEFAULT_BUDGET

WALL_KEYS = ("seconds", "timings", "hybrid_fmu", "model_fmu", "plots", "summary")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default="dc_drive:windage", help="example:variant, comma-separated")
    parser.add_argument("--budget", type=int, default=DEFAULT_BUDGET, help="NeuralFMU loss evaluations")
    args = parser.parse_args()
    try:
        cases = _cases(args.cases)
    except ValueError as exc:
        sys.exit(f"error: {exc}")
    if cores() < 2 or not can_run_beside():
        sys.exit("error: a second process needs two cores and fork(); nothing to compare on this machine")
    folder = Path(tempfile.mkdtemp(prefix="bench_jobs_"))
    print(f"reports in {folder}", flush=True)
    rows = []
    for example, variant in cases:
        train, test = _data(example, variant)
        runs = {}
        for jobs in (1, 2):
            name = f"{example}_{variant}_jobs{jobs}"
            started = time.perf_counter()
            report = hybridize(example_fmu(DECLARED[example]), train, test, folder / f"{name}.fmu", folder / name,
                               budget=args.budget, progress=False, jobs=jobs).report
            runs[jobs] = (time.perf_counter() - started, report)
            print(f"done: {example} {variant}, jobs={jobs} ({runs[jobs][0]:.0f} s)", flush=True)
        (one, first), (two, second) = runs[1], runs[2]
        same = _numbers(first) == _numbers(second)
        rows.append([f"{example} {variant}", f"{one:.0f}", f"{two:.0f}", f"{one / two:.2f}",
                     f"{first['timings']['candidates']:.0f}", f"{second['timings']['candidates']:.0f}",
                     "yes" if same else "**no**"])
    print(f"\nhybridize wall seconds, {args.budget} loss evaluations per training:\n")
    print("| case | jobs=1 | jobs=2 | ratio | candidates, jobs=1 | candidates, jobs=2 | same numbers |")
    print("|---|---|---|---|---|---|---|")
    for row in rows:
        print("| " + " | ".join(row) + " |")


def _numbers(report: dict) -> dict:
    """The report without what the clock and the file names decide."""
    report = json.loads(json.dumps(report))
    for key in WALL_KEYS:
        report.pop(key, None)
    for model in report["models"]:
        model.pop("training_seconds", None)
    return report


if __name__ == "__main__":
    main()
