"""How close each candidate gets to the measurement noise, over every truth variant of the examples.

For each case (an example's truth variant: its training and test data sets, see
fmubuilder/examples_zoo.py) `hybridize` runs as a user would run it: diagnosis, the fitted term and
the NeuralFMU as candidates, the choice on the held-out late share of the training run. Printed per
case and measured signal: the test MSE (the separate test run, held out of everything) divided by
the noise variance of the measured value, for the plain FMU, the fitted term and the NeuralFMU.
1 is the noise floor: a model that matches the truth exactly scores about 1. The noise variance is
the generator's (the sidecar's bench: the sensor's standard deviation squared over the number of
runs averaged); a cell is "-" when the candidate was not built (no significant effect, no term).

The work is counted: `--budget` is the NeuralFMU's epochs (the diagnosis' work is fixed), so the
numbers do not depend on how busy the machine is.

    python benchmarks/bench_effects.py [--cases dc_drive,vldm | dc_drive:stribeck,...] [--budget EPOCHS]
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from fmubuilder.build import example_fmu
from fmubuilder.data import read_sidecar
from fmubuilder.examples_zoo import cached_data, example_data_sets
from fmubuilder.hybridize import hybridize

DECLARED = {"dc_drive": "dc_drive", "vldm": "vldm"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default="dc_drive,vldm",
                        help="examples, or example:variant, comma-separated")
    parser.add_argument("--budget", type=int, default=10, help="NeuralFMU epochs per case")
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="bench_effects_"))
    rows = []
    for example, variant in _cases(args.cases):
        train, test = _data(example, variant)
        started = time.perf_counter()
        result = hybridize(example_fmu(DECLARED[example]), train, test, folder / f"{example}_{variant}.fmu",
                           folder / f"{example}_{variant}", epochs=args.budget, progress=False)
        rows += _rows(f"{example} {variant}", result.report, read_sidecar(test), time.perf_counter() - started)
        print(f"done: {example} {variant} ({time.perf_counter() - started:.0f} s)", flush=True)
    print(f"\nTest MSE / noise variance of the measured value (1 = noise floor), {args.budget} epochs:\n")
    print("| case | signal | plain FMU | fitted term | NeuralFMU | chosen | NeuralFMU channels and inputs |")
    print("|---|---|---|---|---|---|---|")
    for row in rows:
        print("| " + " | ".join(row) + " |")


def _cases(spec: str) -> list[tuple[str, str]]:
    cases = []
    for item in spec.split(","):
        example, _, variant = item.partition(":")
        variants = list(dict.fromkeys(s.variant.key for s in example_data_sets(example)))
        cases += [(example, v) for v in variants if not variant or v == variant]
    return cases


def _data(example: str, variant: str) -> tuple[Path, Path]:
    sets = [s for s in example_data_sets(example) if s.variant.key == variant]
    paths, _ = cached_data(sets)
    by_role = {s.cycle.role: p for s, p in zip(sets, paths)}
    return by_role["train"], by_role["test"]


def _rows(case: str, report: dict, sidecar: dict, seconds: float) -> list[list[str]]:
    bench = sidecar["bench"]
    plain = report["errors"]["test"]["before"]
    models = {m["name"]: m for m in report["models"]}
    neural = models.get("neural")
    described = "-"
    if neural:
        described = f"{neural.get('channel')} <- {', '.join(neural.get('inputs', []))}"
    rows = []
    for signal, errors in plain.items():
        floor = bench["noise_std"][signal] ** 2 / bench["runs"]
        cells = [_ratio(errors["mse"], floor)]
        for name in ("fitted term", "neural"):
            model = models.get(name)
            cells.append(_ratio(errors["mse"] / model["test_mse_factor"][signal], floor) if model else "-")
        rows.append([case, signal, *cells, report["chosen"] or "none", described])
    return rows


def _ratio(mse: float, floor: float) -> str:
    return f"{mse / floor:.3g}"


if __name__ == "__main__":
    main()
