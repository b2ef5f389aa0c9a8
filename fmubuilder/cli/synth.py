"""`fmubuilder synth` (synthetic measurements) and `fmubuilder example`.

The stage modules are imported inside the commands so that the parsers cost nothing at start-up.
"""
from __future__ import annotations

from pathlib import Path

from .common import (guide, non_negative_number, number, parse_assignments, parse_floats, parse_names, positive,
                     positive_number, seed, whole_number)
from .outputs import Plan


def add_synth_parser(subparsers, common=None) -> None:
    from ..synth import DEFAULT_NOISE_STD, DEFAULT_SIGNALS
    defaults = ", ".join(f"{name} {std:g}" for name, std in DEFAULT_NOISE_STD.items())
    p = subparsers.add_parser(
        "synth", parents=[common] if common else [], epilog=guide("docs/data.md"), help="simulate a truth FMU on a test bench and write measured data (CSV + JSON sidecar)",
        description="Simulate a truth FMU and log it as a test bench does: a few signals, sensor lag, "
                    "jittered 10 Hz time stamps, sensor noise, two runs averaged (their spread is written "
                    "as <signal>_std columns). The start values are recorded in <output>.json.")
    p.add_argument("fmu", help="the truth FMU (FMI 2.0 Model Exchange)")
    p.add_argument("--stop-time", type=number, required=True, help="end of the measurement [s]")
    p.add_argument("--start-time", type=number, default=0.0, help="start of the measurement [s] (default 0)")
    p.add_argument("--start", action="append", metavar="NAME=VALUE",
                   help="start value of a parameter, e.g. --start cycle=1 (repeatable)")
    p.add_argument("--signals", default=",".join(DEFAULT_SIGNALS), metavar="A,B,...",
                   help=f"FMU variables to log (default: {','.join(DEFAULT_SIGNALS)})")
    p.add_argument("--seed", type=seed, default=0, help="seed of time stamps and noise (default 0)")
    p.add_argument("--noise", action="append", metavar="NAME=STD",
                   help=f"noise standard deviation of one run, in the signal's unit (repeatable; defaults: {defaults})")
    p.add_argument("--sample-rate", type=positive_number, default=10.0, help="nominal logger rate [Hz] (default 10)")
    p.add_argument("--jitter", type=non_negative_number, default=0.25,
                   help="max deviation of a time stamp from its nominal time, in sample periods (default 0.25)")
    p.add_argument("--lag", type=non_negative_number, default=0.1, help="time constant of the first-order sensor filter [s] (default 0.1)")
    p.add_argument("--runs", type=whole_number(1), default=2, help="repeated runs averaged into the data (default 2)")
    p.add_argument("--run-variation", action="append", metavar="PARAM=REL",
                   help="scale a Real parameter by 1+N(0,REL) in each run, e.g. rolling_coefficient=0.02 (repeatable)")
    p.add_argument("--output", "-o", required=True, metavar="DATA.csv", help="data file to write")
    p.add_argument("--force", action="store_true", help="overwrite existing output files")
    p.set_defaults(func=cmd_synth, plan=lambda args: Plan(
        args.force, files=[("--output", args.output), ("the sidecar of --output", args.output + ".json")],
        inputs=[args.fmu]))


def add_example_parser(subparsers, common=None) -> None:
    p = subparsers.add_parser(
        "example", parents=[common] if common else [], epilog=guide("README.md", "The demo"), help="write an example: FMUs, truth FMUs and measured data sets into a folder",
        description="Write the declared model, its truth variants and synthetic measurements "
                    "(training and test cycle) with a README into a folder.")
    p.add_argument("name", help="example name (available: vldm)")
    p.add_argument("--output", "-o", required=True, metavar="DIR", help="folder to write")
    p.add_argument("--force", action="store_true", help="overwrite the example's files in an existing folder")
    p.set_defaults(func=cmd_example, plan=_example_plan)


def _example_plan(args) -> Plan:
    """The example's files by name: each a regular file or nothing, replaced only with --force."""
    from ..examples_zoo import EXAMPLES, example_data_sets, example_variants
    if args.name not in EXAMPLES:
        return Plan(args.force)     # the command names the examples
    names = {f"{variant.fmu}.fmu" for variant in example_variants(args.name)} | {"README.md"}
    for data_set in example_data_sets(args.name):
        names |= {data_set.file_name, f"{data_set.file_name}.json"}
    return Plan(args.force, into=[("--output", args.output, tuple(sorted(names)))])


def cmd_synth(args) -> None:
    from ..synth import BenchSettings, check_data_path, measure, sidecar_path, write_measurement
    output = Path(args.output)
    settings = BenchSettings(
        signals=tuple(parse_names(args.signals, "--signals")), noise_std=parse_floats(args.noise, "--noise"),
        sample_rate=positive(args.sample_rate, "--sample-rate"), jitter=args.jitter, lag=args.lag,
        runs=args.runs, run_variation=parse_floats(args.run_variation, "--run-variation"), seed=args.seed)
    check_data_path(output, args.force)  # before the simulation, which may take a while
    measurement = measure(args.fmu, start_time=args.start_time, stop_time=args.stop_time,
                          start_values=parse_assignments(args.start), settings=settings)
    write_measurement(measurement, output, force=args.force)
    meta = measurement.metadata
    print(f"wrote {len(measurement.time)} rows of {','.join(measurement.signals)} "
          f"({settings.runs} runs, seed {settings.seed}) to {output}")
    if meta["start_options"]:
        print(f"start values recorded in {sidecar_path(output)}: pass {meta['start_options']} to simulate or train on these data")


def cmd_example(args) -> None:
    from ..examples_zoo import write_example
    write_example(args.name, Path(args.output), force=args.force)

