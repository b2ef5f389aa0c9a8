"""The effect zoo: hybridize on cases drawn at random, scored against the true noise.

For each seed, benchmarks/zoo/generate.py draws a case (a declared FMU, a truth with a missing effect,
a wrong parameter or nothing, and measured data) and writes it with a batch manifest. `hybridize`
runs on each case as a user would run it (declared model, training data, optional validation run,
test data), through `fmubuilder batch` on the generated manifest (a process per case, resumable). Each case is then scored without the report: the shipped hybrid
(or the declared FMU when nothing is shipped) is simulated on the test data, and every measured
signal's test MSE is divided by its true noise variance (of the measured value: a mean over runs
has one run's variance over the number of runs). The truth FMU scored the same way sits near 1:
the column checks the scoring.

Success: every measured signal of the shipped model at most SUCCESS_FACTOR times its noise variance
on the test data, over the seeds with an effect or a wrong parameter. False publish: a hybrid shipped
on a seed without any effect. A case folder that already holds truth.json is reused, and the batch skips the
cases it finished with the same inputs (an interrupted run resumes; give a new --out after changing
the code). Seeds 1000-1049 are reserved for the reported numbers; develop on
seeds below 1000.

    python benchmarks/bench_zoo.py --seeds 1000-1049 [--budget N] [--jobs N] [--out DIR]
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.zoo.generate import build_case, simulate_at, write_manifest  # noqa: E402

SUCCESS_FACTOR = 3.0     # the bar: every measured signal within 3 times its noise variance
# NeuralFMU loss evaluations per case: below hybridize's default (10) so that 50 seeds run in about
# 40 minutes on two cores.
DEFAULT_BUDGET = 3


def parse_seeds(text: str) -> list[int]:
    """'1000-1049' or '1,2,5-7'."""
    seeds = []
    for piece in text.split(","):
        low, _, high = piece.strip().partition("-")
        seeds += list(range(int(low), int(high or low) + 1))
    return seeds


def read_test(case: Path, truth: dict):
    from fmubuilder.data import read_sidecar
    from fmubuilder.simulation import read_csv_signals
    path = case / truth["files"]["test"]
    stamps, columns = read_csv_signals(path)
    start_values = (read_sidecar(path) or {}).get("start_values", {})
    inputs = {k: v for k, v in columns.items() if k not in truth["signals"] and not k.endswith("_std")}
    return stamps, columns, start_values, inputs


def score(fmu: Path, case: Path, truth: dict, parameters: dict | None = None) -> dict[str, float]:
    """Test MSE / true noise variance per measured signal of `fmu` simulated on the test data."""
    stamps, columns, start_values, inputs = read_test(case, truth)
    try:
        simulated = simulate_at(fmu, stamps, truth["signals"], {**start_values, **(parameters or {})}, inputs,
                                rtol=1e-8)
    except Exception as exc:   # a shipped model that cannot run the test scores as infinitely bad
        print(f"  {case.name}: {fmu.name} failed on the test data: {exc}", file=sys.stderr)
        return {s: float("inf") for s in truth["signals"]}
    return {s: float(np.mean((simulated[s] - columns[s]) ** 2) / truth["noise_variance"][s]) for s in truth["signals"]}


def score_case(case: Path, ran: dict, folder: Path) -> dict:
    """The independent scores of a case `fmubuilder batch` ran (`ran`: its summary row; `folder`: its
    outputs): the shipped hybrid, or the declared FMU when nothing was shipped, and the truth."""
    truth = json.loads((case / "truth.json").read_text())
    shipped = folder / "hybrid.fmu" if ran["status"] == "ok" and (folder / "hybrid.fmu").is_file() else None
    row = {"name": case.name, "seed": truth["seed"], "channel": ran["found"] if ran["found"] != "none" else None,
           "chosen": ran["shipped"] if shipped else None,
           "error": ran["reason"] if ran["status"] == "failed" else None,
           "seconds": float(ran["seconds"] or "nan"), "shipped": shipped is not None}
    row["ratios"] = score(shipped or case / "declared.fmu", case, truth)
    truth_params = {k: v["truth"] for k, v in truth["parameters"].items()}
    truth_fmu = case / "truth.fmu" if truth["kind"] == "effect" else case / "declared.fmu"
    row["truth_ratios"] = score(truth_fmu, case, truth, truth_params)
    return row


def generate(seed: int, out: Path) -> tuple[str, dict]:
    """The case of `seed`, drawn and written unless its folder already holds it (a resumed run)."""
    name = f"seed-{seed}"
    written = out / name / "truth.json"
    return name, json.loads(written.read_text()) if written.is_file() else build_case(seed, out / name)


def describe_truth(truth: dict) -> str:
    if truth["kind"] == "effect":
        e = truth["effect"]
        return f"{e['family']} on {e['channel']} reading {','.join(e['inputs'])}"
    if truth["kind"] == "parameter":
        (name, values), = truth["parameters"].items()
        return f"parameter {name} x{values['truth'] / values['declared']:.3g}"
    return "none"


def succeeded(truth: dict, row: dict) -> bool:
    return all(r <= SUCCESS_FACTOR for r in row["ratios"].values())


def table(truths: dict, rows: dict, only: list[str] | None = None) -> list[str]:
    """The markdown table: one row per seed (of `only`, when given)."""
    ratios = lambda r: ", ".join(f"{k} {v:.3g}" for k, v in r.items())
    lines = ["| seed | base | truth | data | channel found | shipped | test MSE / noise variance | truth's | s | ok |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name in only or truths:
        truth = truths[name]
        row, d = rows[name], truth["data"]
        data = (f"{d['rate']:.0f} Hz, {d['runs']} run{'s' * (d['runs'] > 1)}, {d['noise_model']}"
                f"{', std' if d['spread_columns'] else ''}{', val' if d['separate_validation'] else ''}")
        shipped = (row["chosen"] or "?") if row["shipped"] else ("crashed" if row["error"] else "nothing")
        ok = ("no publish" if not row["shipped"] else "PUBLISHED") if truth["kind"] == "none" else \
            ("yes" if succeeded(truth, row) else "no")
        lines.append(f"| {truth['seed']} | {truth['base']} | {describe_truth(truth)} | {data} | {row['channel'] or '-'} "
                     f"| {shipped} | {ratios(row['ratios'])} | {ratios(row['truth_ratios'])} | {row['seconds']:.0f} | {ok} |")
    return lines


def rates(truths: dict, rows: dict) -> list[str]:
    with_effect = [n for n, t in truths.items() if t["kind"] != "none"]
    without = [n for n, t in truths.items() if t["kind"] == "none"]
    wins = sum(succeeded(truths[n], rows[n]) for n in with_effect)
    published = sum(rows[n]["shipped"] for n in without)
    seconds = [rows[n]["seconds"] for n in truths]
    by_kind = {}
    for n in with_effect:
        by_kind.setdefault(truths[n]["kind"], []).append(succeeded(truths[n], rows[n]))
    lines = [f"success: {wins}/{len(with_effect)} seeds with an effect or a wrong parameter "
             f"({100 * wins / max(1, len(with_effect)):.0f} %; "
             + ", ".join(f"{k} {sum(v)}/{len(v)}" for k, v in sorted(by_kind.items())) + ")",
             f"false publish: {published}/{len(without)} seeds without an effect "
             f"({100 * published / max(1, len(without)):.0f} %)",
             f"crashed: {sum(bool(rows[n]['error']) for n in truths)}/{len(truths)} seeds (counted as failures)",
             f"hybridize time per seed: median {np.median(seconds):.0f} s, max {np.max(seconds):.0f} s wall"]
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="1-5", help="e.g. 1000-1049 (reserved) or 1,2,5-9")
    parser.add_argument("--budget", type=int, default=DEFAULT_BUDGET, help="NeuralFMU loss evaluations per case")
    parser.add_argument("--jobs", type=int, default=1, help="cases run side by side")
    parser.add_argument("--out", type=Path, default=None, help="folder of the cases (default: a new temporary one)")
    parser.add_argument("--table-only", action="store_true",
                        help="tabulate the finished cases in --out (of an interrupted or running bench); run nothing")
    args = parser.parse_args(argv)
    out = args.out or Path(__import__("tempfile").mkdtemp(prefix="zoo-"))
    out.mkdir(parents=True, exist_ok=True)
    seeds = parse_seeds(args.seeds)
    started = time.perf_counter()
    if args.table_only:
        truths, rows = finished(out, seeds)
    else:
        truths, rows = run_all(out, seeds, args.budget, args.jobs)
    lines = table(truths, rows) + [""] + rates(truths, rows)
    if len(truths) < len(seeds):
        lines.append(f"(of {len(seeds)} seeds asked for, {len(truths)} finished)")
    (out / "zoo.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"\ntable: {out / 'zoo.md'}; total {time.perf_counter() - started:.0f} s")
    return 0


def run_all(out: Path, seeds: list[int], budget: int, jobs: int) -> tuple[dict, dict]:
    """Generate every case and the manifest, run them with `fmubuilder batch` (as a user runs many
    cases: a process per case, resumable), then score each case independently of its report."""
    from fmubuilder.batch import run_batch
    started = time.perf_counter()
    with ProcessPoolExecutor(jobs) as pool:
        truths = dict(pool.map(generate, seeds, [out] * len(seeds)))
    manifest = write_manifest(out / "manifest.toml", truths, budget)
    print(f"{len(truths)} cases in {out} ({time.perf_counter() - started:.0f} s)", flush=True)
    batch = run_batch(manifest, out / "batch", jobs=jobs, progress=sys.stderr.isatty())
    ran = {r["name"]: r for r in batch.rows}
    with ProcessPoolExecutor(jobs) as pool:
        futures = {pool.submit(score_case, out / name, ran[name], out / "batch" / name): name for name in truths}
        rows = {}
        for future in as_completed(futures):
            row = rows[futures[future]] = future.result()
            (out / row["name"] / "result.json").write_text(json.dumps(row, indent=2) + "\n")
            print(table(truths, {row["name"]: row}, only=[row["name"]])[-1], flush=True)
    return truths, rows


def finished(out: Path, seeds: list[int]) -> tuple[dict, dict]:
    """The scored cases of `seeds` in `out`, scoring those the batch finished since (of a running or
    interrupted bench)."""
    summary = out / "batch" / "summary.csv"
    ran = {r["name"]: r for r in csv.DictReader(summary.open())} if summary.is_file() else {}
    truths, rows = {}, {}
    for seed in seeds:
        case = out / f"seed-{seed}"
        done = case / "result.json"
        if not done.is_file() and ran.get(case.name, {}).get("status") in ("ok", "failed"):
            done.write_text(json.dumps(score_case(case, ran[case.name], out / "batch" / case.name), indent=2) + "\n")
        if done.is_file():
            truths[case.name] = json.loads((case / "truth.json").read_text())
            rows[case.name] = json.loads(done.read_text())
    return truths, rows


if __name__ == "__main__":
    sys.exit(main())
