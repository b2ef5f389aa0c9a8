"""`fmubuilder inspect` and `fmubuilder simulate`."""
from __future__ import annotations

import os
import sys

from ..errors import FmuBuilderError
from ..files import refuse_existing
from .common import guide, number, parse_assignments, parse_names, positive_number
from .outputs import Plan, inputs_with_sidecars


def add_model_parsers(subparsers, common) -> None:
    p = subparsers.add_parser("inspect", parents=[common], epilog=guide("README.md", "Use it on your own FMU and data"),
                              help="list an FMU's variables, states, event indicators and capabilities")
    p.add_argument("fmu", help="path of an FMI 2.0 Model-Exchange FMU")
    p.set_defaults(func=cmd_inspect)

    p = subparsers.add_parser("simulate", parents=[common], epilog=guide("docs/data.md"), help="simulate an FMU with fmubuilder's engine and write a CSV")
    p.add_argument("fmu", help="path of an FMI 2.0 Model-Exchange FMU")
    p.add_argument("--start-time", type=number, default=None, help="default: the FMU's DefaultExperiment or 0")
    p.add_argument("--stop-time", type=number, default=None, help="default: the FMU's DefaultExperiment or 1")
    p.add_argument("--start", action="append", metavar="NAME=VALUE", help="start value of a parameter, state or input (repeatable)")
    p.add_argument("--input", metavar="CSV", help="input signals: a CSV with `time` first, then columns named after FMU inputs")
    p.add_argument("--variables", metavar="A,B,...", help="variables to record (default: outputs and states)")
    p.add_argument("--solver", default="dopri5", choices=["dopri5", "rk4", "euler"], help="default: dopri5 (adaptive)")
    p.add_argument("--rtol", type=positive_number, default=1e-6, help="relative tolerance of the adaptive solver (default 1e-6)")
    p.add_argument("--step-size", type=positive_number, default=None, help="step of the fixed-step solvers (default: the FMU's DefaultExperiment)")
    p.add_argument("--output-interval", type=positive_number, default=None, help="interval of the result rows")
    p.add_argument("--output", "-o", metavar="CSV", help="result file (default: standard output)")
    p.add_argument("--force", action="store_true", help="overwrite an existing output file")
    p.set_defaults(func=cmd_simulate, plan=lambda args: Plan(
        args.force, files=[("--output", args.output)] if args.output else [],
        inputs=inputs_with_sidecars(args.fmu, args.input)))


def cmd_inspect(args) -> None:
    from ..inspect_fmu import describe
    print(describe(args.fmu))


def cmd_simulate(args) -> None:
    from ..simulation import simulate
    output = refuse_existing(args.output, args.force) if args.output else None
    if args.input and os.path.isfile(args.input):
        from ..data import check_plain_numbers
        check_plain_numbers(args.input)
    result = simulate(
        args.fmu, start_time=args.start_time, stop_time=args.stop_time,
        start_values=parse_assignments(args.start), input_csv=args.input,
        variables=parse_names(args.variables), solver=args.solver, rtol=args.rtol,
        step_size=args.step_size, output_interval=args.output_interval)
    _refuse_non_finite(result, args.solver)
    if output:
        result.to_csv(output)
        print(f"wrote {len(result.time)} rows x {len(result.names)} variables to {output}")
    else:
        result.to_csv(sys.stdout)
    print(result.stats_line(), file=sys.stderr)


def _refuse_non_finite(result, solver: str) -> None:
    """A run that left non-finite numbers is an error, never a file of NaN rows with exit code 0."""
    import numpy as np
    for name in result.names:
        values = np.asarray(result[name], dtype=float)
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            at = float(result.time[bad[0]])
            raise FmuBuilderError(
                f"the simulation diverged: {name} is {values[bad[0]]} from t = {at:g} s on ({solver}); nothing "
                "was written: use a smaller --step-size or --solver dopri5, and check the start values")
