"""The `fmubuilder` command line: parse, call one stage function, print.

One module per command group; stages never import this package. Stages are imported
inside their command so that `fmubuilder --help` and `fmubuilder inspect` start fast
(no torch, no onnx).
"""
from __future__ import annotations

import argparse
import functools
import os
import sys
import warnings

from ..errors import FmuBuilderError, first_line
from .common import EXIT_INTERRUPTED, guide

DEFAULT_CALL_TIMEOUT = 60.0


class _Parser(argparse.ArgumentParser):
    """argparse with errors in the house style: one `error:` line that points at --help, exit code 2."""

    def error(self, message: str):
        self.exit(2, f"error: {message}; see `{self.prog} --help`\n")


def build_parser() -> argparse.ArgumentParser:
    from .. import __version__
    from .batch import add_batch_parser
    from .diagnose import add_diagnose_parser
    from .demo import add_demo_parser
    from .export import add_export_parsers
    from .hybridize import add_hybridize_parser
    from .model import add_model_parsers
    from .synth import add_example_parser, add_synth_parser
    from .train import add_train_parser

    parser = _Parser(
        prog="fmubuilder",
        description="Hybrid FMUs from a first-principle FMI 2.0 Model-Exchange FMU and measured data.",
        epilog=guide("README.md") + " Each command's --help names the page for that command.")
    parser.add_argument("--version", action="version", version=f"fmubuilder {__version__}")
    _add_run_options(parser, default=None)
    common = _Parser(add_help=False)
    _add_run_options(common, default=argparse.SUPPRESS)  # SUPPRESS: do not reset options given before the command
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    add_model_parsers(sub, common)
    add_synth_parser(sub, common)
    add_example_parser(sub, common)
    add_train_parser(sub, common)
    add_diagnose_parser(sub, common)
    add_export_parsers(sub, common)
    add_hybridize_parser(sub, common)
    add_batch_parser(sub, common)
    add_demo_parser(sub, common)
    return parser


def _add_run_options(parser: argparse.ArgumentParser, default) -> None:
    group = parser.add_argument_group("running")
    group.add_argument("--debug", action="store_true", default=default,
                       help="show tracebacks of errors")
    group.add_argument("--quiet", "-q", action="store_true", default=default,
                       help="no progress bars (they show only on a terminal anyway, on stderr)")
    from .common import plain_number
    group.add_argument("--call-timeout", type=plain_number, metavar="SECONDS", default=default,
                       help="stop when one call into the FMU's binary takes longer than this "
                            f"(default {DEFAULT_CALL_TIMEOUT:g}; 0: wait forever)")


def parse(argv: list[str] | None):
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return None
    args.debug = bool(getattr(args, "debug", False))
    args.quiet = bool(getattr(args, "quiet", False))
    timeout = getattr(args, "call_timeout", None)
    args.call_timeout = DEFAULT_CALL_TIMEOUT if timeout is None else timeout
    if not args.call_timeout >= 0:
        parser.error(f"--call-timeout {args.call_timeout:g}: give a number of seconds >= 0")
    return args


def run(argv: list[str] | None = None) -> int:
    """Run a command in this process; returns the exit code."""
    args = parse(argv)
    return 2 if args is None else execute(args)


def execute(args, say_interrupt: bool = True) -> int:
    """Call the command's function; every failure becomes one `error:` line and an exit code.
    Warnings (numpy, scipy, torch) are kept back and folded into that line (shown with --debug).
    Under a supervisor (`main`), an interrupt is left for it to say, with what was written."""
    from .. import progress
    if args.quiet:
        progress.set_enabled(False)
    with warnings.catch_warnings(record=not args.debug) as caught:
        warnings.simplefilter("default")
        return _call(args, caught if caught is not None else [], say_interrupt)


def _call(args, caught: list, say_interrupt: bool) -> int:
    try:
        plan = getattr(args, "plan", None)
        if plan is not None:  # every output checked before any work
            from .outputs import check
            check(plan(args))
        args.func(args)
        sys.stdout.flush()
        if caught:  # kept back, but not lost: one line
            print(f"warning: {len(caught)} warning(s) during the command, the first: "
                  f"'{first_line(caught[0].message)}'; rerun with --debug to see them", file=sys.stderr)
    except FmuBuilderError as exc:
        if args.debug:
            raise
        print(f"error: {exc}{_warnings_note(caught)}", file=sys.stderr)
        return 1
    except BrokenPipeError:  # e.g. `fmubuilder inspect x.fmu | head`: the reader has gone
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except KeyboardInterrupt:
        if say_interrupt:
            print("error: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (OverflowError, FloatingPointError) as exc:  # nearly always data far out of range (1e300)
        if args.debug:
            raise
        reason = exc.args[-1] if exc.args and isinstance(exc.args[-1], str) else type(exc).__name__
        print(f"error: a computation overflowed ({reason}){_warnings_note(caught)}; "
              "check the input data for values far outside the model's range", file=sys.stderr)
        return 1
    except Exception as exc:  # a bug, not bad input: still one line unless --debug
        if args.debug:
            raise
        print(f"error: internal error ({type(exc).__name__}: {first_line(exc)}){_warnings_note(caught)}; "
              "rerun with --debug for the traceback", file=sys.stderr)
        return 2
    return 0


def _warnings_note(caught: list) -> str:
    if not caught:
        return ""
    more = f" and {len(caught) - 1} more" if len(caught) > 1 else ""
    return f" (after the warning '{first_line(caught[0].message)}'{more})"


def main(argv: list[str] | None = None) -> int:
    """The `fmubuilder` entry point: the command runs in a supervised worker process, so a
    crashing, exiting or hanging FMU binary ends in one `error:` line (cli/supervise.py)."""
    args = parse(argv)
    if args is None:
        return 2
    from .supervise import run_supervised
    return run_supervised(args, functools.partial(execute, say_interrupt=False))
