"""`fmubuilder hybridize MODEL.fmu --train TRAIN.csv --test TEST.csv -o HYBRID.fmu --report DIR`."""
from __future__ import annotations

from .common import parse_assignments


def add_hybridize_parser(subparsers, common=None) -> None:
    p = subparsers.add_parser(
        "hybridize", parents=[common] if common else [], help="diagnose, add the missing effect, train, export and validate a hybrid FMU, with a report")
    p.add_argument("fmu", metavar="MODEL.fmu", help="the first-principle FMI 2.0 Model-Exchange FMU")
    p.add_argument("--train", required=True, metavar="TRAIN.csv", help="measured data to train on")
    p.add_argument("--train-start", action="append", metavar="NAME=VALUE",
                   help="start value for the training data (repeatable; default: from the data's .json sidecar)")
    p.add_argument("--test", required=True, metavar="TEST.csv", help="held-out measured data")
    p.add_argument("--test-start", action="append", metavar="NAME=VALUE", help="start value for the held-out data")
    p.add_argument("--output", "-o", required=True, metavar="HYBRID.fmu", help="the hybrid FMU to write")
    p.add_argument("--report", required=True, metavar="DIR", help="folder for report.json, report.md and plots")
    p.add_argument("--time-budget", type=float, default=300.0, metavar="SECONDS",
                   help="rough wall-time budget for diagnosis and training (default 300)")
    p.add_argument("--force", action="store_true",
                   help="overwrite outputs, and build a hybrid even when the effect is not significant")
    p.set_defaults(func=cmd_hybridize, outputs=lambda args: [args.output, args.report])


def cmd_hybridize(args) -> None:
    from ..hybridize.workflow import hybridize
    result = hybridize(args.fmu, args.train, args.test, args.output, args.report,
                       train_start=parse_assignments(args.train_start, "--train-start"),
                       test_start=parse_assignments(args.test_start, "--test-start"),
                       time_budget=args.time_budget, force=args.force)
    print(summary(result))


def summary(result) -> str:
    report = result.report
    lines = []
    for part in ("train", "test"):
        for signal, factor in report["mse_factor"][part].items():
            lines.append(f"  {part:5s} {signal:12s} MSE x{factor:.3g} better")
    head = (f"wrote {result.hybrid_fmu}" if result.hybrid_fmu else
            "no hybrid FMU written: " + ("no significant effect" if not report["diagnosis"]["significant"]
                                         else "no candidate improved the held-out error"))
    return "\n".join([head, *lines, f"report: {result.report_dir / 'report.md'}"])
