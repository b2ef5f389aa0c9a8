"""`run_batch`: every case of a manifest through `hybridize`, each in its own process, with a
summary; resumable.

Everything that can be refused is refused before the first case runs: the manifest, the output
folder, each case folder that a new run would replace. Each case is written into a staged folder
beside OUT/<name> and swapped in when its command has ended (files.replace_folder), with its
record (record.py) and its log; a failed case too, so the summary can give its reason. A case
published, and the summary, stay when a later case fails or the batch is interrupted: a re-run
goes on from there.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from ..errors import FmuBuilderError
from ..files import (check_writable_folder, inside, kept_on_failure, kind_of, make_folder, refuse_non_regular,
                     replace_folder, write_atomically)
from ..fmi.side_process import cores
from ..progress import StatusLine, progress as progress_bar
from .case import Outcome, command_line, shown
from .jobs import Job
from .manifest import Case, read_manifest
from .record import RECORD_NAME, case_key, inspect_folder, read_record, read_report, record, refuse_replacing
from .summary import NAMES, counts, row, write_summaries

EXECUTORS = ("local", "ray")
MARKER_NAME = ".fmubuilder-batch.json"     # marks OUT as a batch's: a re-run may write into it
MARKER_FORMAT = "fmubuilder-batch/1"


@dataclass
class BatchResult:
    rows: list[dict]        # the summary's rows, in the manifest's order
    folder: Path

    @property
    def failed(self) -> list[dict]:
        return [r for r in self.rows if r["status"] == "failed"]


def run_batch(manifest, out, *, jobs: int | None = None, executor: str = "local", address: str | None = None,
              force: bool = False, call_timeout: float = 60.0, progress: bool = True) -> BatchResult:
    """Run the manifest's cases into the folder `out`. jobs: cases at once (default: one per core);
    executor: "local" processes or "ray" tasks (address: an existing cluster; default: a local
    one); force: redo the cases an earlier run completed; call_timeout: each case's --call-timeout;
    progress: the bars, and a line per finished case."""
    manifest, out = Path(manifest), Path(out)
    processes = _processes(jobs)
    _check_executor(executor, address)
    cases = read_manifest(manifest)
    _check_output_folder(out, cases)
    keys = {case.name: case_key(case) for case in cases}
    todo = _cases_to_run(cases, keys, out, force)
    _mark_output_folder(out, manifest)
    statuses = {case.name: "pending" if case.name in todo else "skipped" for case in cases}
    batch = _Batch(cases, out, statuses, f"fmubuilder batch: {manifest.name}", progress)
    batch.write_summary()
    side_by_side = min(processes, len(todo))
    work = [Job(case, keys[case.name], command_line(case, _absolute, call_timeout, side_by_side), out / case.name,
                side_by_side, call_timeout) for case in cases if case.name in todo]
    threads = max(1, cores() // max(side_by_side, 1))   # each case's share of the cores for its numeric libraries
    with progress_bar(len(cases), "batch: cases", "case", initial=len(cases) - len(work), show=progress) as bar, \
            StatusLine(show=progress) as line:
        results = _execute(work, executor, processes, threads, address, line.show)
        try:
            for job, outcome in results:
                batch.publish(job, outcome)
                bar.advance()
        finally:
            results.close()     # on the way out early: the cases still running are stopped
            for job in work:    # and their staged folders removed (a published one is gone from there)
                job.discard()
    return BatchResult(batch.rows(), out)


def _cases_to_run(cases: list[Case], keys: dict, out: Path, force: bool) -> set[str]:
    """The names of the cases to run: all with `force`, else those not done under the same key; an
    error, before any work, for a case folder that may not be replaced (record.refuse_replacing)."""
    todo = set()
    for case in cases:
        found = inspect_folder(out / case.name, keys[case.name])
        if force or found.state != "done":
            refuse_replacing(out / case.name, found, force)
            todo.add(case.name)
    return todo


def _mark_output_folder(out: Path, manifest: Path) -> None:
    """OUT made and marked as a batch's, so that a re-run may write into it."""
    with kept_on_failure():
        make_folder(out)
        marker = {"format": MARKER_FORMAT, "manifest": str(manifest.resolve())}
        write_atomically(out / MARKER_NAME, json.dumps(marker) + "\n")


def _processes(jobs: int | None) -> int:
    if jobs is None:
        return cores()
    if not isinstance(jobs, int) or isinstance(jobs, bool) or jobs < 1:
        raise FmuBuilderError(f"jobs must be a whole number of processes >= 1, got {jobs}")
    return jobs


def _check_executor(executor: str, address: str | None) -> None:
    if executor not in EXECUTORS:
        raise FmuBuilderError(f"unknown executor '{executor}': give one of {', '.join(EXECUTORS)}")
    if address and executor != "ray":
        raise FmuBuilderError("--address names a Ray cluster: give --executor ray with it")
    if executor == "ray":
        from .on_ray import import_ray
        import_ray()        # not installed: said now, before any work


def _check_output_folder(out: Path, cases: list[Case]) -> None:
    """OUT is new, empty or an earlier batch's; no case reads a file that a case folder replaces."""
    kind = kind_of(out)
    if kind not in (None, "folder"):
        raise FmuBuilderError(f"the output folder {out} is a {kind}; choose a folder path with -o")
    if kind == "folder" and any(out.iterdir()) and not (out / MARKER_NAME).is_file():
        raise FmuBuilderError(f"the output folder {out} holds files and was not written by fmubuilder batch; choose "
                              "a new or empty folder with -o")
    for name in NAMES:
        refuse_non_regular(out / name)
    _refuse_inputs_in_case_folders(out, cases)
    nearest = out.resolve()
    while not nearest.exists():     # the folder, or the one it is created in, must take a new file
        nearest = nearest.parent
    check_writable_folder(nearest, out)


def _refuse_inputs_in_case_folders(out: Path, cases: list[Case]) -> None:
    for case in cases:
        for path in case.input_files():
            for other in cases:
                if inside(path, out / other.name):
                    raise FmuBuilderError(f"case '{case.name}' reads {path}, inside the case folder {out / other.name} "
                                          "that the batch writes; keep the inputs outside the output folder")


def _absolute(path: Path) -> str:
    """A case's command runs in its own folder: its inputs by their absolute paths."""
    return str(path.resolve())


def _execute(work: list[Job], executor: str, processes: int, threads: int, address: str | None, show):
    """The executor's results as the cases finish: a generator, whose close() stops the cases still
    running."""
    if executor == "ray" and work:
        from .on_ray import run_on_ray
        return run_on_ray(work, processes, threads, address, show)
    from .local import run_locally
    return run_locally(work, processes, threads, show)


class _Batch:
    """The cases' summary rows, their publication and the summary files."""

    def __init__(self, cases: list[Case], out: Path, statuses: dict, title: str, progress: bool):
        self.out, self.title = out, title
        self._rows = {case.name: self._row(case.name, statuses[case.name]) for case in cases}
        self.say = print if progress else (lambda *a, **k: None)

    def publish(self, job: Job, outcome: Outcome) -> None:
        """The case's folder (its results, its record and log) swapped in; the summary rewritten."""
        staging = job.staging()
        command = f"(cd {job.folder} && {shown(job.argv)})"
        write_atomically(staging / RECORD_NAME, json.dumps(record(job.case, job.key, outcome, command), indent=1) + "\n")
        with kept_on_failure():
            replace_folder(staging, job.folder)
            self._rows[job.case.name] = self._row(job.case.name, outcome.status)
            self.write_summary()
        self.say(_line(self._rows[job.case.name]))

    def rows(self) -> list[dict]:
        return list(self._rows.values())

    def write_summary(self) -> None:
        with kept_on_failure():
            write_summaries(self.out, self.rows(), self.title)

    def _row(self, name: str, status: str) -> dict:
        if status == "pending":
            return row(name, status, None, None)
        folder = self.out / name
        return row(name, status, read_record(folder), read_report(folder))


def _line(r: dict) -> str:
    """A finished case in one line, as the batch goes."""
    if r["status"] == "failed":
        return f"{r['name']}: failed: {r['reason']}"
    gain = f", test gain x{r['test_gain']:.3g}" if r["test_gain"] else ""
    return f"{r['name']}: found {r['found']}, shipped {r['shipped']}{gain} ({r['seconds']:.0f} s)"
