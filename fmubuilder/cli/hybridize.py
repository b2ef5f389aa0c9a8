"""`fmubuilder hybridize MODEL.fmu --train TRAIN.csv [--train MORE.csv ...] [--validation VAL.csv]
--test TEST.csv -o HYBRID.fmu --report DIR`."""
from __future__ import annotations

import argparse
import os

from ..errors import FmuBuilderError
from .common import guide, loss_evaluations, parse_assignments, positive_number, processes, seed
from .outputs import Plan, inputs_with_sidecars


class _TrainFile(argparse.Action):
    """--train FILE: one more training file, with its own list of start values."""

    def __call__(self, parser, namespace, value, option_string=None):
        setattr(namespace, self.dest, [*(getattr(namespace, self.dest) or []), (value, [])])


class _TrainStart(argparse.Action):
    """--train-start NAME=VALUE: a start value of the --train file given before it."""

    def __call__(self, parser, namespace, value, option_string=None):
        runs = getattr(namespace, "train") or []
        if not runs:
            parser.error("--train-start belongs to the --train file before it; give --train DATA.csv first")
        runs[-1][1].append(value)


def add_hybridize_parser(subparsers, common=None) -> None:
    from ..hybridize.workflow import DEFAULT_BUDGET, VALIDATION_SHARE
    p = subparsers.add_parser(
        "hybridize", parents=[common] if common else [],
        epilog=guide("docs/how-it-works.md") + " The data it reads: docs/data.md.", help="diagnose, add the missing effect, train, export and validate a hybrid FMU, with a report")
    p.add_argument("fmu", metavar="MODEL.fmu", help="the first-principle FMI 2.0 Model-Exchange FMU")
    p.add_argument("--train", required=True, action=_TrainFile, metavar="TRAIN.csv",
                   help="measured data to train on (repeatable: one run per file)")
    p.add_argument("--train-start", action=_TrainStart, metavar="NAME=VALUE",
                   help="start value for the --train file before it (repeatable; default: the file's .json sidecar)")
    p.add_argument("--validation", metavar="VAL.csv",
                   help="a separate run that chooses the candidate and decides whether to publish it "
                        f"(default: the last {VALIDATION_SHARE:.0%}% of each training run, held out of the fit)")
    p.add_argument("--validation-start", action="append", metavar="NAME=VALUE",
                   help="start value for the validation run")
    p.add_argument("--test", required=True, metavar="TEST.csv",
                   help="test data: touched once, after everything is decided")
    p.add_argument("--test-start", action="append", metavar="NAME=VALUE", help="start value for the test data")
    p.add_argument("--output", "-o", required=True, metavar="HYBRID.fmu", help="the hybrid FMU to write")
    p.add_argument("--report", required=True, metavar="DIR", help="folder for report.json, report.md and plots")
    p.add_argument("--budget", type=loss_evaluations, default=DEFAULT_BUDGET, metavar="N",
                   help="the NeuralFMU training's work in loss evaluations, each a simulation of all training "
                        f"elements with its gradient (default {DEFAULT_BUDGET}); the same number gives the same "
                        "result on any machine")
    p.add_argument("--seed", type=seed, default=0, help="random seed of the training (0 to 2**32-1, default 0)")
    p.add_argument("--time-budget", type=positive_number, default=None, metavar="SECONDS",
                   help="optional wall-clock cap on the training; the report says when it cut the training short "
                        "(the results then depend on the machine)")
    p.add_argument("--allow-insignificant", action="store_true",
                   help="build and publish a hybrid even when the diagnosis finds no significant effect "
                        "(it may then fit noise; the validation data still decide whether one is published)")
    p.add_argument("--ann-on-term", action=argparse.BooleanOptionalAction, default=True,
                   help="also train an ANN that starts from the fitted term and learns what it leaves, whenever a "
                        "term is offered and leaves more than the noise (default: on; --no-ann-on-term leaves it "
                        "out and saves its training)")
    p.add_argument("--jobs", "-j", type=processes, default=None, metavar="N",
                   help="processes for the candidates: 2 trains the NeuralFMU and calibrates beside the fitted "
                        "term, 1 one after the other; the same numbers either way (default: 2 when the machine "
                        "has two cores)")
    p.add_argument("--force", action="store_true",
                   help="overwrite the hybrid FMU and replace a report folder fmubuilder wrote; the old ones stay "
                        "in place until the new ones are complete")
    p.set_defaults(func=cmd_hybridize, plan=_plan)


def _plan(args) -> Plan:
    """The outputs and inputs, and what is wrong with the options, before any work."""
    from ..export.wrapper import check_output_fmu
    from ..files import same_file
    if args.validation_start and not args.validation:
        raise FmuBuilderError("--validation-start belongs to a --validation file; give --validation VAL.csv, or "
                              "--train-start for the training file (its last part is the default validation data)")
    train = [path for path, _ in args.train]
    roles = [("--train", path) for path in train] + [("--validation", args.validation), ("--test", args.test)]
    roles = [(option, path) for option, path in roles if path]
    for i, (option, path) in enumerate(roles):
        for other_option, other in roles[:i]:
            if os.path.isfile(path) and os.path.isfile(other) and same_file(path, other):
                raise FmuBuilderError(f"{option} {path} is also given as {other_option}: data have one role each "
                                      "(the test data are held out of training and choice); give another file")
    check_output_fmu(args.output, force=True)       # its name; the existing file is the plan's check
    return Plan(args.force, files=[("--output", args.output)], folders=[("--report", args.report)],
                inputs=inputs_with_sidecars(args.fmu, *train, args.validation, args.test))


def cmd_hybridize(args) -> None:
    from ..export.wrapper import check_model_identifier
    from ..fmi import read_model_info
    from ..hybridize.workflow import hybridize
    # a name the export refuses, found now rather than after the training
    check_model_identifier(read_model_info(args.fmu).model_identifier, args.fmu)
    train = [path for path, _ in args.train]
    train_start = [parse_assignments(starts, "--train-start") for _, starts in args.train]
    result = hybridize(args.fmu, train, args.test, args.output, args.report, validation_csv=args.validation,
                       train_start=train_start,
                       validation_start=parse_assignments(args.validation_start, "--validation-start"),
                       test_start=parse_assignments(args.test_start, "--test-start"), budget=args.budget,
                       seed=args.seed, time_budget=args.time_budget, force=args.force,
                       allow_insignificant=args.allow_insignificant, ann_on_term=args.ann_on_term,
                       jobs=args.jobs)
    print(summary(result))


def summary(result) -> str:
    report = result.report
    lines = []
    for part in ("train", "validation", "test"):
        for signal, factor in report["mse_factor"][part].items():
            lines.append(f"  {part:10s} {signal:12s} MSE x{factor:.3g} better")
    if report.get("selection", {}).get("scores"):
        scores = ", ".join(f"{name} {score:.3g}" for name, score in report["selection"]["scores"].items())
        selection = report["selection"]
        lines.append(f"  validation MSE / noise variance, geometric mean over the signals (chooses; plain FMU "
                     f"{selection.get('plain_score', float('nan')):.3g}, an ANN must beat the simpler by "
                     f"x{selection.get('margin', 1.0):.3g}): {scores}")
    for name, why in report.get("selection", {}).get("not_trained", {}).items():
        lines.append(f"  not trained: {name}; {why}")
    for name, why in report.get("selection", {}).get("failed", {}).items():
        lines.append(f"  failed: {name}; {why}")
    if report["models"]:
        lines.append("  test MSE relative to the plain FMU, mean over the signals (touched once, after the choice): " +
                     ", ".join(f"{m['name']} {m['test_relative_mse']:.3g}" for m in report["models"]))
        lines.append(f"  test MSE / noise variance, geometric mean over the signals (the validation score's measure; "
                     f"plain FMU {report.get('test_plain_score', float('nan')):.3g}): " +
                     ", ".join(f"{m['name']} {m.get('test_score', float('nan')):.3g}" for m in report["models"]))
    if result.hybrid_fmu:
        head = f"wrote {result.hybrid_fmu}"
    elif not report["models"] and not report["diagnosis"]["significant"]:
        head = "no hybrid FMU written: no significant effect (--allow-insignificant builds one anyway)"
    else:
        head = "no hybrid FMU written: no candidate improved the validation error"
    return "\n".join([head, *lines, f"report: {result.report_dir / 'report.md'}"])
