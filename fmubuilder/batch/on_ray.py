"""The Ray executor: each case a Ray task, on this machine (a local cluster) or on an existing
cluster (`address`).

A task gets the case and its input files' bytes (each file put in the object store once, however
many cases read it), writes them into a scratch folder on its worker, runs the case's command
there as the local executor does (case.py) and returns the outcome with the case's folder as a
tar archive; the caller unpacks it into the case's staged folder. A task whose worker dies is
retried once (max_retries=1), then reported as the case's failure. Ray is an optional extra
(`pip install fmubuilder[ray]`); every worker needs fmubuilder installed.
"""
from __future__ import annotations

import io
import tarfile
import tempfile
from pathlib import Path
from typing import Callable, Iterator

from ..errors import FmuBuilderError, first_line
from .case import INTERRUPT_WAIT, Outcome, command_line, run_case
from .jobs import Job
from .manifest import Case

WAIT = 0.5          # seconds between redraws of the stage line
RETRIES = 1         # a task whose worker died runs once more


def import_ray():
    try:
        import ray
    except ImportError:
        raise FmuBuilderError("--executor ray needs Ray, which is not installed: pip install 'fmubuilder[ray]' "
                              "(or pip install ray), or use the local executor") from None
    return ray


def run_on_ray(jobs: list[Job], processes: int, threads: int, address: str | None,
               show: Callable[[list[str]], None]) -> Iterator[tuple[Job, Outcome]]:
    """Yields each job with its outcome as it finishes. Without `address`, a local cluster of
    `processes` CPUs is started and stopped again."""
    ray = import_ray()
    started_here = not ray.is_initialized()
    if started_here:
        _start(ray, address, processes)
    pending: dict = {}
    try:
        task = ray.remote(num_cpus=1, max_retries=RETRIES)(_run_remote)
        blobs: dict[Path, object] = {}
        for job in jobs:
            files = job.case.input_files()
            for path in files:
                if path.resolve() not in blobs:
                    blobs[path.resolve()] = ray.put(path.read_bytes())
            ref = task.remote(job.case, job.side_by_side, job.call_timeout, threads, files,
                              *(blobs[path.resolve()] for path in files))
            pending[ref] = job
        while pending:
            show([f"{len(pending)} case(s) queued or running on Ray"])
            done, _ = ray.wait(list(pending), num_returns=1, timeout=WAIT)
            for ref in done:
                job = pending.pop(ref)
                yield job, _collect(ray, ref, job)
    finally:
        _cancel(ray, list(pending))
        if started_here:
            ray.shutdown()


def _cancel(ray, refs: list) -> None:
    """Stop the tasks still queued or running; a running one interrupts its case's command (run_case)
    and gets the time to clean up."""
    for ref in refs:
        ray.cancel(ref)
    if refs:
        ray.wait(refs, num_returns=len(refs), timeout=INTERRUPT_WAIT + 1)


def _start(ray, address: str | None, processes: int) -> None:
    try:
        if address:
            ray.init(address=address, logging_level="ERROR", log_to_driver=False)
        else:
            ray.init(num_cpus=processes, include_dashboard=False, logging_level="ERROR", log_to_driver=False)
    except Exception as exc:    # Ray raises ConnectionError, RuntimeError, ValueError, ...
        where = f"the Ray cluster at {address}" if address else "a local Ray cluster"
        raise FmuBuilderError(f"cannot start or reach {where}: {first_line(exc)}; check --address (e.g. "
                              "ray://HOST:10001 or auto) or run without --executor ray") from None


def _collect(ray, ref, job: Job) -> Outcome:
    """The task's outcome, its folder unpacked into the job's staged folder."""
    try:
        outcome, archive = ray.get(ref)
    except ray.exceptions.RayError as exc:
        return Outcome("failed", f"the Ray task failed ({type(exc).__name__}: {first_line(exc)}), "
                                 f"also when retried {RETRIES} time(s)")
    safe = {"filter": "data"} if hasattr(tarfile, "data_filter") else {}   # Python 3.11.4 and later
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(job.staging(), **safe)
    return outcome


def _run_remote(case: Case, side_by_side: int, call_timeout: float, threads: int, files: list[Path],
                *contents: bytes) -> tuple[Outcome, bytes]:
    """On a Ray worker: the case's input files written where its command reads them, the case run,
    its folder returned as a tar archive."""
    with tempfile.TemporaryDirectory(prefix="fmubuilder-batch-") as scratch:
        copies = _write_inputs(Path(scratch) / "inputs", files, contents)
        folder = Path(scratch) / "case"
        folder.mkdir()
        argv = command_line(case, lambda path: str(copies[path]), call_timeout, side_by_side)
        outcome = run_case(argv, folder, threads)
        return outcome, _archive(folder)


def _write_inputs(root: Path, files: list[Path], contents: tuple[bytes, ...]) -> dict[Path, Path]:
    """Each input in a folder for its original folder, so a data file keeps its sidecar beside it
    and two files of one name from two folders stay apart."""
    folders: dict[Path, Path] = {}
    copies = {}
    for path, content in zip(files, contents):
        folder = folders.setdefault(path.parent, root / str(len(folders)))
        folder.mkdir(parents=True, exist_ok=True)
        copies[path] = folder / path.name
        copies[path].write_bytes(content)
    return copies


def _archive(folder: Path) -> bytes:
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as tar:
        for path in sorted(folder.iterdir()):
            tar.add(path, arcname=path.name)
    return buffer.getvalue()
