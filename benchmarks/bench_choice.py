"""Does the choice on the validation data pick the candidate that is best on the test data?

For each DC drive case `hybridize` runs with its default candidates; then the rule before (the
lowest mean over the signals of validation MSE / MSE of the plain FMU, the ANN on the fitted term
not yet a candidate) and the rule now (hybridize/choice.py: geometric mean of MSE / noise variance,
a noise margin for the ANN candidates) are applied to the same validation errors. Each choice is
compared with the best candidate on the test data by three judges: the worst signal's test MSE /
noise variance (the project's target: at most 3 on every signal), the geometric mean of test MSE /
noise variance, and the mean of test MSE / MSE plain (the rule before, on the test data). The test
data choose nothing here either: they only judge.

    python benchmarks/bench_choice.py [--cases stribeck,coulomb,...] [--budget EPOCHS]
"""
from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path

from bench_effects import _data

from fmubuilder.build import example_fmu
from fmubuilder.fmi import read_model_info
from fmubuilder.hybridize import hybridize
from fmubuilder.hybridize.evaluate import read_data

ADDED = "neural on the fitted term"      # not a candidate before


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default="stribeck,coulomb,speed_current_loss,two_effects")
    parser.add_argument("--budget", type=int, default=5, help="NeuralFMU loss evaluations per training")
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="bench_choice_"))
    info = read_model_info(example_fmu("dc_drive"))
    hits = {"before": [0, 0, 0], "now": [0, 0, 0]}
    print("| case | candidate | validation: mean MSE / MSE plain | validation score (now) | test worst MSE / noise | "
          "test geometric mean MSE / noise | test mean MSE / MSE plain | chosen before | chosen now |")
    print("|---|---|---|---|---|---|---|---|---|")
    variants = args.cases.split(",")
    for variant in variants:
        train, test = _data("dc_drive", variant)
        report = hybridize(example_fmu("dc_drive"), train, test, folder / f"{variant}.fmu", folder / variant,
                           budget=args.budget, progress=False).report
        noise = read_data(test, info)
        floors = {s: noise.noise_variance(s) for s in noise.names}
        selection = report["selection"]
        relative = selection["relative_to_plain"]
        old_set = {name: r for name, r in relative.items() if name != ADDED}
        before = min(old_set, key=old_set.get) if min(old_set.values()) < 1.0 else None
        now = selection["chosen"]
        judged = _judges(report, floors)
        for name in relative:
            worst, geo, mean = (j[name] for j in judged)
            print(f"| {variant} | {name} | {relative[name]:.3g} | {selection['scores'][name]:.3g} | {worst:.3g} | "
                  f"{geo:.3g} | {mean:.3g} | {'yes' if name == before else ''} | {'yes' if name == now else ''} |",
                  flush=True)
        for rule, chosen, names in (("before", before, old_set), ("now", now, relative)):
            for k, judge in enumerate(judged):
                hits[rule][k] += chosen == min(names, key=judge.get)
    print(f"\nChosen = best on test, of {len(variants)} cases (judges: worst signal / geometric mean / mean "
          "relative to the plain FMU):")
    for rule, counts in hits.items():
        print(f"  {rule}: " + " / ".join(str(c) for c in counts))


def _judges(report: dict, floors: dict) -> tuple[dict, dict, dict]:
    """Per candidate: worst signal's test MSE / noise, geometric mean of it, mean MSE / MSE plain."""
    plain = {s: v["mse"] for s, v in report["errors"]["test"]["before"].items()}
    worst, geo, mean = {}, {}, {}
    for model in report["models"]:
        mse = {s: plain[s] / model["test_mse_factor"][s] for s in plain}
        over = [mse[s] / floors[s] for s in plain]
        worst[model["name"]] = max(over)
        geo[model["name"]] = math.exp(sum(math.log(x) for x in over) / len(over))
        mean[model["name"]] = sum(mse[s] / plain[s] for s in plain) / len(plain)
    return worst, geo, mean


if __name__ == "__main__":
    main()
