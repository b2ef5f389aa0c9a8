"""`fmubuilder export` and `fmubuilder validate`:

    fmubuilder export TRAINED -o HYBRID.fmu [--force]
    fmubuilder validate HYBRID.fmu [--against TRAINED] [--data DATA.csv] [--start NAME=VALUE]...

TRAINED is a hybrid spec JSON (spec.py) or a trained NeuralFMU file, which the neural
stage turns into a spec. `validate` prints a table and exits non-zero when the round trip
misses its tolerances.
"""
from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

from ..errors import FmuBuilderError
from .common import guide, parse_assignments, positive_number
from .outputs import Plan


def add_export_parsers(subparsers, common=None) -> None:
    """Add the `export` and `validate` commands to an argparse subparsers object."""
    parents = [common] if common else []
    p = subparsers.add_parser("export", parents=parents, epilog=guide("docs/export.md"), help="export a trained hybrid model as an FMI 2.0 Model-Exchange FMU")
    p.add_argument("trained", metavar="TRAINED", help="hybrid spec JSON or trained NeuralFMU file")
    p.add_argument("--output", "-o", required=True, metavar="HYBRID.fmu", help="the FMU to write")
    p.add_argument("--force", action="store_true", help="overwrite an existing output file")
    p.set_defaults(func=cmd_export, plan=_export_plan)

    p = subparsers.add_parser("validate", parents=parents, epilog=guide("docs/export.md"), help="check an exported hybrid FMU against the Python reference")
    p.add_argument("fmu", metavar="HYBRID.fmu", help="hybrid FMU written by `fmubuilder export`")
    p.add_argument("--against", metavar="TRAINED",
                   help="hybrid spec JSON or trained NeuralFMU file (default: the spec stored in the FMU)")
    p.add_argument("--data", metavar="DATA.csv", help="input signals and time span: `time`, then FMU input columns")
    p.add_argument("--start", action="append", metavar="NAME=VALUE",
                   help="start value of a parameter, state or gate, e.g. hybrid.v.p_ann=0 (repeatable)")
    p.add_argument("--stop-time", type=positive_number, default=None, help="default: the FMU's DefaultExperiment")
    p.add_argument("--step-size", type=positive_number, default=None,
                   help="fixed step and output interval (default: the FMU's DefaultExperiment stepSize)")
    p.set_defaults(func=cmd_validate)


def _export_plan(args) -> Plan:
    from ..export.wrapper import check_output_fmu
    check_output_fmu(args.output, force=True)   # the name (.fmu); the existing file is the plan's check
    return Plan(args.force, files=[("--output", args.output)], inputs=[args.trained])


def _wrapped_fmus(trained: str) -> list[str]:
    """The FMU a spec JSON or a trained NeuralFMU file wraps (an input too), when it names one."""
    import json
    path = Path(trained)
    if not path.is_file():
        return []
    if _looks_like_json(path):
        try:
            data = json.loads(path.read_text())
            return [str(path.resolve().parent / data["original_fmu"])]
        except (OSError, ValueError, KeyError, TypeError):
            return []   # the export reports what is wrong with the spec
    from ..neural.io import read_neural_fmu
    try:
        return [str(read_neural_fmu(path)["fmu"]["path"])]
    except (FmuBuilderError, KeyError, TypeError):
        return []


def cmd_export(args) -> None:
    from ..export.wrapper import export_hybrid, platform_note
    from ..files import same_file
    for fmu in _wrapped_fmus(args.trained):
        if os.path.lexists(args.output) and same_file(args.output, fmu):
            raise FmuBuilderError(f"--output {args.output} is the FMU {args.trained} wraps, an input of the export; "
                                  "give the hybrid another path")
    with _spec_from(args.trained) as spec:
        output = export_hybrid(spec, args.output, force=args.force)
        print(f"wrote {output} ({platform_note(spec.original_fmu, output)})")


def cmd_validate(args) -> None:
    from ..export.validate import validate_hybrid
    with contextlib.ExitStack() as stack:
        spec = stack.enter_context(_spec_from(args.against)) if args.against else None
        report = validate_hybrid(args.fmu, spec=spec, data_csv=args.data, start_values=parse_assignments(args.start),
                                 stop_time=args.stop_time, step_size=args.step_size)
    print(report.format_table())
    if not report.passed:
        raise FmuBuilderError("the hybrid FMU failed the round-trip validation (see the table above)")


@contextlib.contextmanager
def _spec_from(trained: str):
    """A HybridSpec from a spec JSON, or from a trained NeuralFMU file via the neural stage
    (its ONNX file lives in a temporary folder for the duration of the command)."""
    from ..export.spec import HybridSpec
    path = Path(trained)
    if not path.is_file():
        raise FmuBuilderError(f"{path}: no such file; give a hybrid spec JSON or a trained NeuralFMU file")
    if _looks_like_json(path):
        yield HybridSpec.load(path)
        return
    from ..hybridize.terms import to_hybrid_spec
    with tempfile.TemporaryDirectory(prefix="fmubuilder-spec-") as folder:
        spec = to_hybrid_spec(path, Path(folder))
        yield spec if isinstance(spec, HybridSpec) else HybridSpec.load(spec)


def _looks_like_json(path: Path) -> bool:
    with open(path, "rb") as file:
        return file.read(64).lstrip().startswith(b"{")

