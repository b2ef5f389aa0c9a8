"""`fmubuilder diagnose MODEL.fmu --data DATA.csv`: the diagnosis stage on the command line."""
from __future__ import annotations

import json
import math

from ..errors import FmuBuilderError
from ..files import make_folder, refuse_existing, write_atomically
from .common import guide, number, parse_assignments
from .outputs import Plan, inputs_with_sidecars

PLOT_NAMES = ("signals.png", "residuals.png", "residual_vs_inputs.png")   # diagnose/plots.py


def add_diagnose_parser(subparsers, common=None) -> None:
    p = subparsers.add_parser(
        "diagnose", parents=[common] if common else [], epilog=guide("docs/how-it-works.md"),
        help="compare a model with measured data: errors, is it more than noise, where is an effect missing",
        description="Simulate the declared model against measured data, test whether the residual exceeds the "
                    "measurement noise and, if so, trace it to the state derivative and the variables a missing "
                    "term depends on.")
    p.add_argument("fmu", help="the declared model: an FMI 2.0 Model-Exchange FMU")
    p.add_argument("--data", required=True, metavar="CSV",
                   help="measured data: `time` first, then signals named after FMU variables (optional <signal>_std)")
    p.add_argument("--start", action="append", metavar="NAME=VALUE",
                   help="start value of a parameter or state (repeatable; added to the data's sidecar values)")
    p.add_argument("--json", metavar="OUT.json", help="write the full diagnosis as JSON")
    p.add_argument("--plots", metavar="DIR", help="write PNG plots into this folder")
    p.add_argument("--time-budget", type=number, default=None, metavar="SECONDS",
                   help="optional upper cap on the tracing's wall time; the report says when it cut the tracing "
                        "short (default: none; the tracing's work is fixed by the model and the data)")
    p.add_argument("--force", action="store_true", help="overwrite an existing JSON file and plots")
    p.set_defaults(func=cmd_diagnose, plan=lambda args: Plan(
        args.force, files=[("--json", args.json)] if args.json else [],
        into=[("--plots", args.plots, PLOT_NAMES)] if args.plots else [],
        inputs=inputs_with_sidecars(args.fmu, args.data)))


def cmd_diagnose(args) -> None:
    from ..diagnose.diagnosis import diagnose

    if args.time_budget is not None and not (math.isfinite(args.time_budget) and args.time_budget > 0):
        raise FmuBuilderError(f"--time-budget {args.time_budget:g}: give a positive number of seconds")
    json_path = refuse_existing(args.json, args.force) if args.json else None
    if args.plots:
        make_folder(args.plots)     # recorded: a failed run removes it again when it made it
    result = diagnose(args.fmu, args.data, start_values=parse_assignments(args.start), plots_dir=args.plots,
                      time_budget=args.time_budget)
    print(result.report())
    if json_path is not None:
        write_atomically(json_path, json.dumps(result.to_dict(), indent=2) + "\n")
        print(f"wrote {json_path}")
    for path in result.plots:
        print(f"wrote {path}")
