"""The fitted term before and after its coefficient is refined through the simulation.

For each DC drive truth variant (fmubuilder/examples_zoo.py: its training and test runs) the
diagnosis runs on the training samples `hybridize` fits on (the first 80 % of the training run),
its term is exported, and hybridize/refine_term.py refines its coefficient on the same samples.
Printed:

1. per variant: the term's form, the truth's coefficient (read from the variant's C definition,
   examples_zoo.dc_drive_truth_term; "-" for effects that are no such term), the coefficient the
   diagnosis fitted and the refined one, the simulations the refinement took, and its objective
   (mean squared residual in noise units on the training samples) before and after;
2. per variant and signal: the test run's MSE (held out of everything) divided by the noise
   floor (the generator's noise variance of the logged mean), for the plain FMU, the diagnosed
   term and the refined term, simulated accurately (DOPRI5, rtol 1e-7), and the refined term once
   more with the scoring's checked RK4, as `hybridize` compares candidates.

    python benchmarks/bench_fitted_term.py [--variants windage,extra_heating,...]
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from fmubuilder.build import example_fmu
from fmubuilder.data import read_sidecar
from fmubuilder.diagnose import diagnose
from fmubuilder.examples_zoo import cached_data, dc_drive_truth_term, example_data_sets, example_variants
from fmubuilder.export import export_hybrid
from fmubuilder.fmi import read_model_info
from fmubuilder.hybridize.evaluate import Scoring, evaluate, read_data
from fmubuilder.hybridize.refine_term import (ACCURATE_RTOL, coefficients_text, refine_scales, scaled_term,
                                              term_gates)
from fmubuilder.hybridize.terms import spec_from_fitted_term
from fmubuilder.hybridize.workflow import VALIDATION_SHARE


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", default=",".join(v.key for v in example_variants("dc_drive")
                                                       if v.key != "no_effect"),
                        help="DC drive truth variants, comma-separated")
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="bench_fitted_term_"))
    coefficients, errors = [], []
    for variant in args.variants.split(","):
        started = time.perf_counter()
        result = _case(variant, folder / variant)
        if result is not None:
            coefficients.append(result[0])
            errors += result[1]
        print(f"done: {variant} ({time.perf_counter() - started:.0f} s)", flush=True)
    print("\nCoefficient of the fitted term, before and after the refinement through the simulation:\n")
    print("| variant | term | truth | diagnosis | refined | simulations | objective before | objective after |")
    print("|---|---|---|---|---|---|---|---|")
    for row in coefficients:
        print("| " + " | ".join(row) + " |")
    print(f"\nTest MSE / noise floor (1 = the floor); DOPRI5 rtol {ACCURATE_RTOL:g} unless said:\n")
    print("| variant | signal | plain FMU | diagnosed term | refined term | refined term, the scoring's checked RK4 |")
    print("|---|---|---|---|---|---|")
    for row in errors:
        print("| " + " | ".join(row) + " |")


def _case(variant: str, folder: Path):
    fmu = example_fmu("dc_drive")
    info = read_model_info(fmu)
    sets = [s for s in example_data_sets("dc_drive") if s.variant.key == variant]
    paths, _ = cached_data(sets)
    by_role = {s.cycle.role: p for s, p in zip(sets, paths)}
    run = read_data(by_role["train"], info)
    train = run.window(run.start, run.start + (1.0 - VALIDATION_SHARE) * (run.stop - run.start))
    diagnosis = diagnose(fmu, train, run.start_values)
    fitted = diagnosis.fitted_term
    if not fitted or not fitted.get("offered"):
        print(f"{variant}: the diagnosis offers no term")
        return None
    folder.mkdir(parents=True)
    start_values = {**run.start_values, **diagnosis.start_values}
    diagnosed, gates = _hybrid(fitted, fmu, info, folder / "diagnosed")
    scoring = Scoring.checked(fmu, train, start_values)
    noise = {e.signal: e.noise for e in diagnosis.errors}
    refinement = refine_scales(diagnosed, gates, [(train, start_values)], noise, scoring.step, show=False)
    refined_term = scaled_term(fitted, refinement.scales[0])
    refined, _ = _hybrid(refined_term, fmu, info, folder / "refined")
    truth = dc_drive_truth_term(variant)
    forms = [f"c{k + 1} * {t['form']}" if len(fitted["terms"]) > 1 else f"c * {t['form']}"
             for k, t in enumerate(fitted["terms"])]
    form = f"{fitted['channel']} += {' + '.join(forms)}".replace("|", "\\|")     # a markdown table cell
    coefficients = [variant, f"`{form}`", f"{truth['coefficient']:.7g}" if truth else "-",
                    coefficients_text(fitted), coefficients_text(refined_term) if refinement.kept else "kept",
                    str(refinement.simulations), f"{refinement.objective_before:.4g}",
                    f"{refinement.objective_after:.4g}"]
    test = read_data(by_role["test"], info)
    bench = read_sidecar(by_role["test"])["bench"]
    accurate = Scoring.accurate(scoring.step, ACCURATE_RTOL)
    runs = [evaluate(model, test, test.start_values, how).errors
            for model, how in ((fmu, accurate), (diagnosed, accurate), (refined, accurate), (refined, scoring))]
    rows = []
    for signal in test.names:
        floor = bench["noise_std"][signal] ** 2 / bench["runs"]
        rows.append([variant, signal, *(f"{errors[signal]['mse'] / floor:.3g}" for errors in runs)])
    return coefficients, rows


def _hybrid(fitted: dict, fmu: Path, info, folder: Path):
    folder.mkdir()
    spec = spec_from_fitted_term(fitted, fmu, info.guid, folder)
    return export_hybrid(spec, folder / "hybrid.fmu"), term_gates(spec)


if __name__ == "__main__":
    main()
