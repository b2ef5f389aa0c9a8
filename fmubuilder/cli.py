"""The `fmubuilder` command line: parse, call one stage function, print.

Stages are imported inside their command so that `fmubuilder --help` and
`fmubuilder inspect` start fast (no torch, no onnx).
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from .errors import FmuBuilderError


def parse_assignments(items: list[str] | None, option: str = "--start") -> dict[str, str]:
    """Parse repeated NAME=VALUE options into a dict (values stay strings; the FMU's
    variable types decide their conversion)."""
    values = {}
    for item in items or []:
        name, sep, value = item.partition("=")
        if not sep or not name.strip() or not value.strip():
            raise FmuBuilderError(f"malformed {option} '{item}': write {option} NAME=VALUE, e.g. {option} mass=1000")
        values[name.strip()] = value.strip()
    return values


def parse_names(text: str | None) -> list[str] | None:
    if text is None:
        return None
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise FmuBuilderError("empty variable list: give comma-separated names, e.g. --variables h,v")
    return names


def check_output_path(path: str | Path, force: bool) -> Path:
    path = Path(path)
    if path.exists() and not force:
        raise FmuBuilderError(f"{path} exists; choose another output path or pass --force to overwrite it")
    return path


# -- commands -------------------------------------------------------------------------------

def cmd_inspect(args) -> None:
    from .inspect_fmu import describe
    print(describe(args.fmu))


def cmd_simulate(args) -> None:
    from .simulation import simulate
    output = check_output_path(args.output, args.force) if args.output else None
    result = simulate(
        args.fmu, start_time=args.start_time, stop_time=args.stop_time,
        start_values=parse_assignments(args.start), input_csv=args.input,
        variables=parse_names(args.variables), solver=args.solver, rtol=args.rtol,
        step_size=args.step_size, output_interval=args.output_interval)
    if output:
        result.to_csv(output)
        print(f"wrote {len(result.time)} rows x {len(result.names)} variables to {output}")
    else:
        result.to_csv(sys.stdout)
    print(result.stats_line(), file=sys.stderr)


def cmd_demo(args) -> None:
    from .demo import run_demo
    run_demo(Path(args.output), force=args.force, time_budget=args.time_budget)


def build_parser() -> argparse.ArgumentParser:
    from . import __version__
    parser = argparse.ArgumentParser(
        prog="fmubuilder",
        description="Hybrid FMUs from a first-principle FMI 2.0 Model-Exchange FMU and measured data.")
    parser.add_argument("--version", action="version", version=f"fmubuilder {__version__}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks of errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("inspect", help="list an FMU's variables, states, event indicators and capabilities")
    p.add_argument("fmu", help="path of an FMI 2.0 Model-Exchange FMU")
    p.set_defaults(func=cmd_inspect)

    p = sub.add_parser("simulate", help="simulate an FMU with fmubuilder's engine and write a CSV")
    p.add_argument("fmu", help="path of an FMI 2.0 Model-Exchange FMU")
    p.add_argument("--start-time", type=float, default=None, help="default: the FMU's DefaultExperiment or 0")
    p.add_argument("--stop-time", type=float, default=None, help="default: the FMU's DefaultExperiment or 1")
    p.add_argument("--start", action="append", metavar="NAME=VALUE", help="start value of a parameter, state or input (repeatable)")
    p.add_argument("--input", metavar="CSV", help="input signals: a CSV with `time` first, then columns named after FMU inputs")
    p.add_argument("--variables", metavar="A,B,...", help="variables to record (default: outputs and states)")
    p.add_argument("--solver", default="dopri5", choices=["dopri5", "rk4", "euler"], help="default: dopri5 (adaptive)")
    p.add_argument("--rtol", type=float, default=1e-6, help="relative tolerance of the adaptive solver (default 1e-6)")
    p.add_argument("--step-size", type=float, default=None, help="step of the fixed-step solvers (default: the FMU's DefaultExperiment)")
    p.add_argument("--output-interval", type=float, default=None, help="interval of the result rows")
    p.add_argument("--output", "-o", metavar="CSV", help="result file (default: standard output)")
    p.add_argument("--force", action="store_true", help="overwrite an existing output file")
    p.set_defaults(func=cmd_simulate)

    from .diagnose.cli import add_diagnose_parser
    from .export.cli import add_export_parsers
    from .hybridize.cli import add_hybridize_parser
    from .neural.cli import add_train_parser
    from .synth_cli import add_example_parser, add_synth_parser
    add_synth_parser(sub)
    add_example_parser(sub)
    add_train_parser(sub)
    add_diagnose_parser(sub)
    add_export_parsers(sub)
    add_hybridize_parser(sub)

    p = sub.add_parser("demo", help="run the whole workflow on the bundled example and write a report")
    p.add_argument("--output", "-o", default="fmubuilder-demo", help="output folder (default: ./fmubuilder-demo)")
    p.add_argument("--force", action="store_true", help="replace an existing output folder")
    p.add_argument("--time-budget", type=float, default=None, metavar="SECONDS",
                   help="optional wall-clock cap on the training (default: none; the work is counted in epochs)")
    p.set_defaults(func=cmd_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        args.func(args)
    except FmuBuilderError as exc:
        if args.debug:
            raise
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except BrokenPipeError:  # e.g. `fmubuilder inspect x.fmu | head`: the reader has gone
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # a bug, not bad input: still one line unless --debug
        if args.debug:
            raise
        print(f"error: internal error ({type(exc).__name__}: {exc}); rerun with --debug for the traceback",
              file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
