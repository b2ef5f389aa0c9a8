"""The local executor: each case's command in a process of its own, up to `processes` at a time.

A thread per running case waits on its process and reads its stage lines; the caller's thread
does everything else (staging folders, publishing), one case after the other as they finish.
"""
from __future__ import annotations

import threading
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from typing import Callable, Iterator

from ..errors import first_line
from .case import INTERRUPT_WAIT, Outcome, Run, interrupt
from .jobs import Job

WAIT = 0.5                  # seconds between redraws of the stage line


def run_locally(jobs: list[Job], processes: int, threads: int,
                show: Callable[[list[str]], None]) -> Iterator[tuple[Job, Outcome]]:
    """Yields each job with its outcome as it finishes; `show` gets the running cases' stages."""
    running: dict[str, Run] = {}
    lock = threading.Lock()
    stopping = threading.Event()

    def work(job: Job) -> Outcome:
        with lock:
            if stopping.is_set():
                return Outcome("failed", "interrupted")
            try:
                running[job.case.name] = Run(job.argv, job.staging(), threads)
            except OSError as exc:
                return Outcome("failed", f"cannot start the case's command: {first_line(exc)}")
        try:
            return running[job.case.name].finish()
        finally:
            with lock:
                running.pop(job.case.name, None)

    waiting = list(jobs)
    pool = ThreadPoolExecutor(max_workers=processes, thread_name_prefix="case")
    started: dict = {}
    try:
        while waiting or started:
            while waiting and len(started) < processes:     # staged here, in the caller's thread
                job = waiting.pop(0)
                job.staging()
                started[pool.submit(work, job)] = job
            done, _ = wait(started, timeout=WAIT, return_when=FIRST_COMPLETED)
            for future in done:
                yield started.pop(future), future.result()
            with lock:
                show([f"{name}: {run.stage}" for name, run in running.items()])
    finally:
        stopping.set()
        with lock:
            runs = list(running.values())
        interrupt(runs, INTERRUPT_WAIT)
        pool.shutdown(wait=True, cancel_futures=True)
