"""One case: its `fmubuilder hybridize` command, run in a process of its own.

The command runs as a user would run it, so each case gets everything the command line gives a
single run: the FMU in a supervised worker (cli/supervise.py), so that a binary that crashes,
exits or hangs ends that case with one line naming the FMI call, and the clean-up of a failed run.
It writes `hybrid.fmu` and `report/` into the folder it runs in (the case's staged folder); its
output goes to `log.txt` there, which also holds the command, to rerun the case alone.
"""
from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ..files import JOURNAL_ENV
from .manifest import Case

HYBRID_NAME = "hybrid.fmu"
REPORT_NAME = "report"
LOG_NAME = "log.txt"
# the stage lines hybridize prints: "[2/5] training a NeuralFMU ..."
STAGE_LINE = re.compile(r"^\[(\d+)/(\d+)\] (.*?)(?: \.\.\.)?$")
THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")
# seconds an interrupted case's command gets to clean up, within the 5 that the batch's own
# supervisor gives the batch (cli/supervise.py INTERRUPT_GRACE); one still running then is killed
INTERRUPT_WAIT = 3.0
PACKAGE_ROOT = Path(__file__).resolve().parents[2]      # the folder that holds fmubuilder/


@dataclass
class Outcome:
    status: str             # "ok" (hybridize ran to its end) or "failed"
    reason: str = ""        # the failure in one line
    seconds: float = 0.0    # wall time of the case's command


def command_line(case: Case, where: Callable[[Path], str], call_timeout: float, side_by_side: int) -> list[str]:
    """The case's `fmubuilder hybridize` arguments; `where` gives the path to pass for each input
    file (the file itself, or its copy on a Ray worker). With other cases running side by side, a
    case trains its candidates one after the other unless its options say otherwise (the numbers
    are the same either way)."""
    argv = ["hybridize", where(case.model)]
    for train, starts in zip(case.train, case.train_start):
        argv += ["--train", where(train), *_starts("--train-start", starts)]
    if case.validation is not None:
        argv += ["--validation", where(case.validation), *_starts("--validation-start", case.validation_start)]
    argv += ["--test", where(case.test), *_starts("--test-start", case.test_start)]
    argv += ["-o", HYBRID_NAME, "--report", REPORT_NAME]
    options = dict(case.options)
    if side_by_side > 1:
        options.setdefault("jobs", 1)
    argv += _option_arguments(options)
    return argv + ["--call-timeout", f"{call_timeout:g}", "--quiet"]


def _starts(option: str, starts: dict) -> list[str]:
    return [part for name, value in starts.items() for part in (option, f"{name}={value}")]


def _option_arguments(options: dict) -> list[str]:
    argv = []
    for key, value in options.items():
        flag = "--" + key.replace("_", "-")
        if key == "ann_on_term":
            argv.append(flag if value else "--no-ann-on-term")
        elif isinstance(value, bool):
            argv += [flag] if value else []
        else:
            argv += [flag, repr(value) if isinstance(value, float) else str(value)]
    return argv


def shown(argv: list[str]) -> str:
    """The command as a user types it."""
    import shlex
    return "fmubuilder " + " ".join(shlex.quote(part) for part in argv)


class Run:
    """The case's command running in `folder`; `stage` is its latest stage line."""

    def __init__(self, argv: list[str], folder: Path, threads: int):
        self.argv, self.folder = argv, folder
        self.stage = "starting"
        self.started = time.perf_counter()
        self.log = open(folder / LOG_NAME, "w", encoding="utf-8")
        self.log.write(f"$ {shown(argv)}\n")
        self.log.flush()
        try:
            self.process = self._start(argv, folder, threads)
        except BaseException:
            self.log.close()
            raise

    @staticmethod
    def _start(argv: list[str], folder: Path, threads: int) -> subprocess.Popen:
        # a process group of its own: the case's supervisor, its worker and the worker's helper are
        # interrupted, or killed, as one (interrupt)
        return subprocess.Popen([sys.executable, "-m", "fmubuilder.cli", *argv], cwd=folder, env=_environment(threads),
                                stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                start_new_session=True)

    def finish(self) -> Outcome:
        """Read its output to the end, keeping the stage up to date; the outcome when it has ended."""
        last_error = ""
        try:
            for line in self.process.stdout:
                self.log.write(line)
                line = line.rstrip("\n")
                if line.startswith("error: "):
                    last_error = line[len("error: "):]
                stage = STAGE_LINE.match(line)
                if stage:
                    self.stage = f"{stage[1]}/{stage[2]} {stage[3]}"
            code = self.process.wait()
        finally:
            self.process.stdout.close()
            self.log.close()
        seconds = time.perf_counter() - self.started
        if code == 0:
            return Outcome("ok", "", seconds)
        return Outcome("failed", last_error or _exit_reason(code), seconds)


def interrupt(runs: list[Run], wait: float) -> None:
    """Interrupt the cases' commands as Ctrl-C does (each cleans up what it wrote); kill the process
    group of one that has not ended after `wait` seconds (an FMU stuck in a call cannot see it)."""
    for run in runs:
        _signal_group(run.process, signal.SIGINT)
    deadline = time.monotonic() + wait
    for run in runs:
        try:
            run.process.wait(max(deadline - time.monotonic(), 0.01))
        except subprocess.TimeoutExpired:
            _signal_group(run.process, signal.SIGKILL)
            run.process.wait()


def _signal_group(process: subprocess.Popen, sig: int) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(process.pid, sig)


def run_case(argv: list[str], folder: Path, threads: int = 1) -> Outcome:
    """Run a case's command in `folder` to its end (a Ray task's way); when the caller is interrupted
    (a cancelled task), the command is too."""
    run = Run(argv, folder, threads)
    try:
        return run.finish()
    except BaseException:
        interrupt([run], INTERRUPT_WAIT)
        raise


def _environment(threads: int) -> dict:
    """The command's environment: its output unbuffered (the stage lines arrive as they are printed),
    its numeric libraries on its share of the cores (the same on every executor: Ray sets its own
    otherwise), no journal of the batch's own (a case's command keeps one of its own)."""
    env = {key: value for key, value in os.environ.items() if key != JOURNAL_ENV}
    env["PYTHONUNBUFFERED"] = "1"
    # this fmubuilder, also when it was found through the current folder (the case runs in another)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(PACKAGE_ROOT), env.get("PYTHONPATH")]))
    for variable in THREAD_VARIABLES:
        env[variable] = str(threads)
    return env


def _exit_reason(code: int) -> str:
    if code < 0:
        return f"the case's process was killed ({signal.Signals(-code).name})"
    return f"the case's command ended with exit code {code} and no message; see its {LOG_NAME}"
