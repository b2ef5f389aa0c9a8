"""How close each candidate gets to the measurement noise, over every truth variant of the examples.

For each case (an example's truth variant: its training and test data sets, see
fmubuilder/examples_zoo.py) `hybridize` runs as a user would run it: diagnosis, the fitted term and
the NeuralFMU as candidates, the choice on the held-out late share of the training run. Printed per
case and measured signal: the test MSE (the separate test run, held out of everything) divided by
the noise variance of the measured value, for the truth FMU (the model that made the data), the
plain FMU, the best calibrated parameter (of the calibrated candidates, the one with the lowest
validation score), the fitted term, the NeuralFMU and the ANN on the fitted term. 1 is the noise
floor: the truth column shows that the scoring (`Scoring.checked`, the same for every column)
reaches it, so the other columns measure the models, not the integrator. The noise variance is the
generator's (the sidecar's bench: the sensor's standard deviation squared over the number of runs
averaged); a cell is "-" when the candidate was not built (no significant effect, no term, or a
term at the noise floor, on which no ANN is trained). The seconds are the case's wall time (the
whole hybridize call; with --truth-only the step check and the truth's run).

The work is counted: `--budget` is the NeuralFMU's loss evaluations (each a simulation of all
training elements with gradient; the diagnosis' work is fixed), so the numbers do not depend on how
busy the machine is. `--optimizer` trains with another optimizer than hybridize's default, on the
same budget (`adam` or `lbfgs`), to compare them;
`--elements N` cuts the training data into at least N elements (hybridize: MIN_ELEMENTS).
`--warm-start-target pointwise|integral` and `--integral-window S` set the NeuralFMU's warm start
target (neural/warm_start.py). `--truth-only` scores the truth FMU alone: a quick check of the scoring.

    python benchmarks/bench_effects.py [--cases dc_drive,vldm | dc_drive:stribeck,...] [--budget EVALUATIONS]
                                       [--optimizer adam|lbfgs] [--elements N]
                                       [--warm-start-target pointwise|integral] [--integral-window S]
                                       [--truth-only]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

from fmubuilder.build import example_fmu
from fmubuilder.data import read_sidecar
from fmubuilder.examples_zoo import EXAMPLES, cached_data, example_data_sets
from fmubuilder.fmi import read_model_info
from fmubuilder.hybridize import hybridize
from fmubuilder.hybridize.evaluate import Scoring, evaluate, read_data
from fmubuilder.hybridize import recipe
from fmubuilder.hybridize.workflow import DEFAULT_BUDGET, VALIDATION_SHARE

DECLARED = {"dc_drive": "dc_drive", "vldm": "vldm"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default="dc_drive,vldm",
                        help="examples, or example:variant, comma-separated")
    parser.add_argument("--budget", type=int, default=DEFAULT_BUDGET, help="NeuralFMU loss evaluations per training")
    parser.add_argument("--optimizer", default=None, choices=["adam", "lbfgs"],
                        help="the training's optimizer (default: hybridize's)")
    parser.add_argument("--elements", type=int, default=None,
                        help="at least this many training elements (default: hybridize's)")
    parser.add_argument("--warm-start-target", choices=["pointwise", "integral"], default=None,
                        help="the NeuralFMU's warm start target (default: hybridize's)")
    parser.add_argument("--integral-window", type=float, default=None,
                        help="seconds per window of the integral warm start target (default: hybridize's)")
    parser.add_argument("--last-layer", type=int, default=None,
                        help="simulations of the last layer's refinement per loss evaluation (default: hybridize's)")
    parser.add_argument("--truth-only", action="store_true",
                        help="score the truth FMU alone (checks the scoring; no hybridize)")
    args = parser.parse_args()
    try:
        cases = _cases(args.cases)
        if args.optimizer:
            recipe.OPTIMIZER = args.optimizer
        if args.warm_start_target:
            recipe.WARM_START_TARGET = args.warm_start_target
        if args.integral_window is not None:
            if not args.integral_window > 0:
                raise ValueError(f"--integral-window: give positive seconds, got {args.integral_window}")
            recipe.INTEGRAL_WINDOW = args.integral_window
        if args.last_layer is not None:
            recipe.LAST_LAYER_SIMULATIONS_PER_EVALUATION = args.last_layer
        if args.elements is not None:
            if args.elements < 1:
                raise ValueError(f"--elements: give 1 or more, got {args.elements}")
            recipe.MIN_ELEMENTS = args.elements
    except ValueError as exc:
        sys.exit(f"error: {exc}")
    folder = Path(tempfile.mkdtemp(prefix="bench_effects_"))
    print(f"reports in {folder}", flush=True)
    rows = []
    for example, variant in cases:
        train, test = _data(example, variant)
        started = time.perf_counter()
        scoring, truth = _truth_errors(example, variant, train, test)
        report = None
        if not args.truth_only:
            report = hybridize(example_fmu(DECLARED[example]), train, test, folder / f"{example}_{variant}.fmu",
                               folder / f"{example}_{variant}", budget=args.budget, progress=False).report
        seconds = time.perf_counter() - started
        rows += _rows(f"{example} {variant}", truth, report, read_sidecar(test), seconds)
        print(f"done: {example} {variant} ({seconds:.0f} s), {scoring.describe()}", flush=True)
    optimizer = recipe.OPTIMIZER
    print(f"\nTest MSE / noise variance of the measured value (1 = noise floor), {args.budget} loss evaluations "
          f"({optimizer}, at least {recipe.MIN_ELEMENTS} elements, warm start target {recipe.WARM_START_TARGET}"
          + (f" over {recipe.INTEGRAL_WINDOW:g} s" if recipe.WARM_START_TARGET == "integral" else "") + "):\n")
    print("| case | signal | truth FMU | plain FMU | calibrated | fitted term | NeuralFMU | ANN on the term | chosen "
          "| NeuralFMU channels and inputs | seconds |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        print("| " + " | ".join(row) + " |")


def _cases(spec: str) -> list[tuple[str, str]]:
    cases = []
    for item in spec.split(","):
        example, _, variant = item.strip().partition(":")
        if example not in EXAMPLES:
            raise ValueError(f"--cases: unknown example '{example}'; choose among {', '.join(EXAMPLES)}")
        variants = list(dict.fromkeys(s.variant.key for s in example_data_sets(example)))
        if variant and variant not in variants:
            raise ValueError(f"--cases: {example} has no variant '{variant}'; choose among {', '.join(variants)}")
        cases += [(example, v) for v in variants if not variant or v == variant]
    return cases


def _truth_errors(example: str, variant: str, train: Path, test: Path) -> tuple[Scoring, dict]:
    """The truth FMU's test errors, scored as hybridize scores every model: the step checked with the
    declared FMU on the training samples (the run without its held-out late share)."""
    declared = example_fmu(DECLARED[example])
    info = read_model_info(declared)
    train_data = read_data(train, info)
    split = train_data.start + (1.0 - VALIDATION_SHARE) * (train_data.stop - train_data.start)
    scoring = Scoring.checked(declared, train_data.window(train_data.start, split), train_data.start_values)
    data_set = next(s for s in example_data_sets(example) if s.variant.key == variant)
    test_data = read_data(test, info)
    starts = {**test_data.start_values, **data_set.variant.truth_parameters}
    return scoring, evaluate(example_fmu(data_set.variant.fmu), test_data, starts, scoring).errors


def _data(example: str, variant: str) -> tuple[Path, Path]:
    sets = [s for s in example_data_sets(example) if s.variant.key == variant]
    paths, _ = cached_data(sets)
    by_role = {s.cycle.role: p for s, p in zip(sets, paths)}
    return by_role["train"], by_role["test"]


def _rows(case: str, truth: dict, report: dict | None, sidecar: dict, seconds: float) -> list[list[str]]:
    bench = sidecar["bench"]
    models = {m["name"]: m for m in report["models"]} if report else {}
    calibrated = [name for name in models if name.startswith("calibrated ")]
    if calibrated:
        models["calibrated"] = models[min(calibrated, key=lambda name: report["selection"]["scores"][name])]
    neural = models.get("neural")
    described = "-"
    if neural:
        described = f"{neural.get('channel')} <- {', '.join(neural.get('inputs', []))}"
        per_channel = neural.get("channel_inputs") or {}
        if any(names != neural.get("inputs") for names in per_channel.values()):
            described = "; ".join(f"{c} <- {', '.join(names)}" for c, names in per_channel.items())
    rows = []
    for signal, truth_errors in truth.items():
        floor = bench["noise_std"][signal] ** 2 / bench["runs"]
        cells = [_ratio(truth_errors["mse"], floor)]
        if report:
            plain = report["errors"]["test"]["before"][signal]["mse"]
            cells.append(_ratio(plain, floor))
            for name in ("calibrated", "fitted term", "neural", "neural on the fitted term"):
                model = models.get(name)
                cells.append(_ratio(plain / model["test_mse_factor"][signal], floor) if model else "-")
        else:
            cells += ["-"] * 5
        chosen = (report["chosen"] or "none") if report else "-"
        rows.append([case, signal, *cells, chosen, described, f"{seconds:.0f}"])
    return rows


def _ratio(mse: float, floor: float) -> str:
    return f"{mse / floor:.3g}"


if __name__ == "__main__":
    main()
