"""`fmubuilder demo`: hybridize on the bundled example."""
from __future__ import annotations

from pathlib import Path

from ..files import write_manifest
from .common import guide, positive_number
from .hybridize import summary


def add_demo_parser(subparsers, common) -> None:
    p = subparsers.add_parser(
        "demo", parents=[common], epilog=guide("README.md", "The demo"), help="run the whole workflow on the bundled example and write a report",
        description="Write the VLDM example (a declared vehicle model without its extra driving resistance, "
                    "the truth FMUs and measured data sets) into the output folder, then run `fmubuilder "
                    "hybridize` on the extra-resistance data: diagnose the missing effect, fit a term and train "
                    "a NeuralFMU, choose on the held-out validation part, score the test cycle once, export, "
                    "validate the round trip and write the report. Progress shows on stderr; about 10 minutes "
                    "on two cores, longer on the first run (the example FMUs are built and their data "
                    "simulated once, then cached).")
    p.add_argument("--output", "-o", default="fmubuilder-demo", help="output folder (default: ./fmubuilder-demo)")
    p.add_argument("--force", action="store_true",
                   help="replace an output folder an earlier demo wrote; it is kept until the new run succeeds")
    p.add_argument("--time-budget", type=positive_number, default=None, metavar="SECONDS",
                   help="optional wall-clock cap on the training (default: none; the work is counted in loss evaluations)")
    p.set_defaults(func=cmd_demo, plan=_plan)


def _plan(args):
    from .outputs import Plan
    return Plan(args.force, folders=[("--output", args.output)])   # --force replaces only an earlier demo


def cmd_demo(args) -> None:
    from ..demo import run_demo
    result, example = run_demo(Path(args.output), force=args.force, time_budget=args.time_budget)
    write_manifest(args.output)     # marks the folder as the demo's: a later --force may replace it
    print(summary(result))
    print(f"\nThe other data sets in {example}/ (extra_loss_*, no_effect_*) work the same way, e.g.\n"
          f"  fmubuilder hybridize {example}/vldm.fmu --train {example}/extra_loss_train_cadc.csv "
          f"--test {example}/extra_loss_test_wltc2.csv -o loss_hybrid.fmu --report loss_report")
