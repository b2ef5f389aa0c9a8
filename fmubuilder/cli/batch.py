"""`fmubuilder batch MANIFEST -o OUT [--jobs N] [--executor local|ray] [--address ADDR] [--force]`."""
from __future__ import annotations

from ..errors import FmuBuilderError
from .common import guide, processes


def add_batch_parser(subparsers, common) -> None:
    p = subparsers.add_parser(
        "batch", parents=[common], epilog=guide("docs/batch.md"),
        help="run hybridize on every case a manifest lists, in parallel, with a summary; resumable",
        description="Run `fmubuilder hybridize` on each case of a TOML manifest (model, data, start values, "
                    "options), each in a process of its own: a case that fails, or whose FMU crashes, is that "
                    "case's failure only. Writes OUT/<case>/hybrid.fmu and OUT/<case>/report/, and "
                    "OUT/summary.csv, .md and .html. A re-run skips the cases done with the same inputs and "
                    "options and reruns the failed or unfinished ones.")
    p.add_argument("manifest", metavar="MANIFEST.toml", help="the cases (format: docs/batch.md)")
    p.add_argument("--output", "-o", required=True, metavar="OUT", help="folder for the cases' results and the summary")
    p.add_argument("--jobs", "-j", type=processes, default=None, metavar="N",
                   help="cases at once (default: one per core); with more than one, each case trains its "
                        "candidates one after the other unless its options give jobs")
    p.add_argument("--executor", choices=("local", "ray"), default="local",
                   help="local processes (default) or Ray tasks (pip install 'fmubuilder[ray]')")
    p.add_argument("--address", metavar="ADDR",
                   help="with --executor ray: an existing Ray cluster (e.g. auto, ray://HOST:10001); default: a "
                        "local cluster of --jobs CPUs, started for the batch")
    p.add_argument("--force", action="store_true",
                   help="redo the cases an earlier run completed (their folders are replaced when the new run "
                        "of the case succeeds)")
    # its cases finish one by one and stay, for a re-run to resume: no 'nothing was written'
    p.set_defaults(func=cmd_batch, keeps_finished_work=True)


def cmd_batch(args) -> None:
    from ..batch import run_batch
    from ..batch.summary import counts
    result = run_batch(args.manifest, args.output, jobs=args.jobs, executor=args.executor, address=args.address,
                       force=args.force, call_timeout=args.call_timeout)
    print(f"{counts(result.rows)}; summary: {result.folder / 'summary.md'}")
    if result.failed:
        first = result.failed[0]
        raise FmuBuilderError(f"{len(result.failed)} of {len(result.rows)} case(s) failed, the first "
                              f"'{first['name']}': {first['reason']}; the summary lists each; a re-run retries "
                              "the failed cases and skips the others")
