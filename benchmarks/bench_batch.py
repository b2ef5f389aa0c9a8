"""`fmubuilder batch`: N cases on 1 and 2 local processes and on a local Ray cluster.

The cases: the DC drive against its windage truth, each with its own noise seeds (train 0-6 s,
test 20.5-24 s), budget 0 and no ANN on the term (the fitted term and the calibrations: about 20 s
of one core each); `--truth dc_drive`: against its own model (a diagnosis that finds nothing,
about 4 s each: the batch's own cost, and Ray's, weigh more). Printed: the wall seconds of each run, as a ratio against one local process;
Ray's cluster start (once per batch without --address) and its overhead per case (the Ray run
against two local processes, the same two CPUs, its cluster already up); and whether the three
summaries hold the same results (they must: each case runs the same command). Measure on an
otherwise idle machine with two cores; the ratios are the point, not the seconds.

    python benchmarks/bench_batch.py [--cases N] [--budget N] [--truth dc_drive]
"""
from __future__ import annotations

import argparse
import csv
import sys
import tempfile
import time
from pathlib import Path

from fmubuilder import synth
from fmubuilder.batch import run_batch
from fmubuilder.build import example_fmu
from fmubuilder.fmi.side_process import cores

NOISE = dict(signals=("speed", "current", "power", "temperature"),
             noise_std={"speed": 0.1, "current": 0.02, "power": 1.0, "temperature": 0.02})
TRAIN, TEST = (0.0, 6.0), (20.5, 24.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=4, help="cases in the batch (default 4)")
    parser.add_argument("--budget", type=int, default=0, help="NeuralFMU loss evaluations per case (default 0)")
    parser.add_argument("--truth", default="dc_drive_truth_windage", help="the example FMU that makes the data")
    args = parser.parse_args()
    if cores() < 2:
        sys.exit("error: two local processes need two cores; nothing to compare on this machine")
    folder = Path(tempfile.mkdtemp(prefix="bench_batch_"))
    manifest = write_cases(folder, args.cases, args.budget, args.truth)
    print(f"{args.cases} cases in {manifest}", flush=True)
    walls, summaries = {}, {}
    for label, options in (("local, 1 process", dict(jobs=1)), ("local, 2 processes", dict(jobs=2))):
        walls[label], summaries[label] = timed_batch(manifest, folder / f"local-{options['jobs']}", **options)
    ray_start = None
    try:
        import ray
        started = time.perf_counter()
        ray.init(num_cpus=2, include_dashboard=False, logging_level="ERROR", log_to_driver=False)
        ray_start = time.perf_counter() - started
        label = "Ray, local cluster of 2 CPUs"
        walls[label], summaries[label] = timed_batch(manifest, folder / "ray", jobs=2, executor="ray")
        ray.shutdown()
    except ImportError:
        print("Ray is not installed (pip install 'fmubuilder[ray]'): its row is left out", flush=True)
    report(walls, summaries, ray_start, args.cases)


def write_cases(folder: Path, count: int, budget: int, truth: str) -> Path:
    data = folder / "data"
    data.mkdir()
    truth = example_fmu(truth)
    lines = [f"[defaults]\nbudget = {budget}\nann_on_term = false\n"]
    for i in range(count):
        for role, window, seed in (("train", TRAIN, i), ("test", TEST, 1000 + i)):
            measurement = synth.measure(truth, start_time=window[0], stop_time=window[1],
                                        settings=synth.BenchSettings(seed=seed, **NOISE))
            synth.write_measurement(measurement, data / f"case{i}_{role}.csv")
        lines.append(f'[[case]]\nname = "case{i}"\nmodel = "{example_fmu("dc_drive")}"\n'
                     f'train = "data/case{i}_train.csv"\ntest = "data/case{i}_test.csv"\n')
    manifest = folder / "cases.toml"
    manifest.write_text("\n".join(lines))
    return manifest


def timed_batch(manifest: Path, out: Path, **options) -> tuple[float, list[dict]]:
    started = time.perf_counter()
    result = run_batch(manifest, out, progress=False, **options)
    wall = time.perf_counter() - started
    print(f"done: {out.name} ({wall:.0f} s)", flush=True)
    with open(out / "summary.csv", newline="") as handle:
        rows = [{k: v for k, v in r.items() if k != "seconds"} for r in csv.DictReader(handle)]
    assert not result.failed, result.failed
    return wall, rows


def report(walls: dict, summaries: dict, ray_start: float | None, count: int) -> None:
    one = walls["local, 1 process"]
    print(f"\nfmubuilder batch, {count} cases, wall seconds:\n")
    print("| executor | wall [s] | against 1 process |")
    print("|---|---|---|")
    for label, wall in walls.items():
        print(f"| {label} | {wall:.0f} | {wall / one:.2f} |")
    if ray_start is not None:
        overhead = (walls["Ray, local cluster of 2 CPUs"] - walls["local, 2 processes"]) / count
        print(f"\nRay: cluster start {ray_start:.1f} s (once per batch); overhead per case against two local "
              f"processes {overhead:+.2f} s")
    reference = next(iter(summaries.values()))
    same = all(rows == reference for rows in summaries.values())
    print(f"same summaries (all but the time): {'yes' if same else '**no**'}")


if __name__ == "__main__":
    main()
