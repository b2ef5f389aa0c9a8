"""Run a command in a forked worker that an FMU's binary cannot take down with the tool.

The parent forks once per command and waits; the whole simulation runs in the worker, so
no FMI call crosses a process boundary. The worker reports its exit code in the shared
breadcrumb page (fmi/breadcrumb.py) before it exits; a worker that dies by a signal, exits
without that report (an exit() inside the FMU) or stays inside one FMI call longer than
--call-timeout is reported by the parent from the breadcrumb in one `error:` line. A helper the
worker runs beside it (fmi/side_process.py) leaves its crumbs on a page of its own: the parent
watches its calls the same way and stops it with the worker.

The parent also owns the command's temporary folder (the worker's TMPDIR: extracted FMUs,
build folders) and removes it on every exit path. After a failure it removes what the command
created, and only that: the paths the worker recorded in its journal (files.py: its staged files
and folders, the outputs it created where nothing was), each only while it is still the one the
command made; never a file another process wrote meanwhile or one the user had.
"""
from __future__ import annotations

import contextlib
import math
import os
import select
import shutil
import signal
import sys
import tempfile
import time
from pathlib import Path

from ..files import JOURNAL_ENV, remove_created
from ..fmi import breadcrumb
from ..fmi.breadcrumb import CALL, HELPER, PID_SLOT, PING_SLOT, REPORT_SLOT, REPORTED
from .common import EXIT_INTERRUPTED, EXIT_TERMINATED

INTERRUPT_GRACE = 5.0       # seconds the worker gets to stop cleanly after Ctrl-C
EXIT_HANG = 124             # as timeout(1)
EXIT_UNEXPECTED = 3         # the worker ended with exit code 0 but never reported


def run_supervised(args, execute) -> int:
    """Run `execute(args)` in a worker process; returns the command's exit code."""
    outputs = _declared_outputs(args)
    before = {path: _fingerprint(path) for path in outputs}
    temp_root = Path(tempfile.mkdtemp(prefix="fmubuilder-run-"))
    journal = temp_root / "created.jsonl"
    pid, code, message, hint = None, 2, "", ""
    try:
        breadcrumb.reset()
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            try:
                _worker(args, execute, temp_root, journal)
            finally:
                os._exit(2)  # never run the parent's code in the worker
        code, message, hint = _Supervisor(pid, args.call_timeout).wait()
    except KeyboardInterrupt:  # before the supervisor's own handlers were in place
        if pid:
            _send(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
        code, message, hint = EXIT_INTERRUPTED, "interrupted", ""
    finally:
        _stop_helper()   # a worker that died cannot stop its helper
        if code != 0:
            remove_created(journal)
        shutil.rmtree(temp_root, ignore_errors=True)
    if code != 0:
        changed = [str(path) for path, fingerprint in before.items() if _fingerprint(path) != fingerprint]
        if message and not getattr(args, "keeps_finished_work", False):
            message += "; " + ("written before the failure: " + ", ".join(changed) if changed else "nothing was written")
    if message and hint:
        message += "; " + hint
    if message:
        print(f"error: {message}", file=sys.stderr)
    return code


# -- worker --------------------------------------------------------------------------------

def _worker(args, execute, temp_root: Path, journal: Path) -> None:
    code = 2
    try:
        os.environ["TMPDIR"] = str(temp_root)  # for the worker and the tools it starts
        os.environ[JOURNAL_ENV] = str(journal)  # what it creates, for the clean-up of a failure
        tempfile.tempdir = str(temp_root)
        signal.signal(signal.SIGUSR1, _answer_ping)
        signal.siginterrupt(signal.SIGUSR1, False)  # a ping must not fail the FMU's system calls
        signal.signal(signal.SIGINT, _interrupt_once)
        breadcrumb.watch_fmpy()
        code = execute(args)
    except KeyboardInterrupt:  # before the command started: the supervisor says it
        code = EXIT_INTERRUPTED
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    except BaseException:  # --debug re-raises: show the traceback, then report
        import traceback
        traceback.print_exc()
        code = 2
    finally:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        CALL[REPORT_SLOT] = REPORTED + code
        os._exit(code)


def _answer_ping(signum, frame) -> None:
    CALL[PING_SLOT] = 0


_interrupted = False


def _interrupt_once(signum, frame) -> None:
    """Ctrl-C reaches the worker twice (terminal and parent): stop once, then clean up undisturbed."""
    global _interrupted
    if not _interrupted:
        _interrupted = True
        raise KeyboardInterrupt


# -- parent --------------------------------------------------------------------------------

class _Supervisor:
    def __init__(self, pid: int, call_timeout: float):
        self.pid = pid
        self.call_timeout = call_timeout
        self.poll = min(0.2, call_timeout / 10) if call_timeout > 0 else 0.2
        self.worker = _Watch(CALL, lambda: pid, helper=False)
        self.helper = _Watch(HELPER, lambda: HELPER[PID_SLOT], helper=True) if HELPER is not None else None
        self.interrupted_at: float | None = None
        self.terminated = False
        self.pidfd = _open_pidfd(pid)

    def wait(self) -> tuple[int, str, str]:
        """(exit code, message for the user or "" when the worker reported itself, hint)"""
        previous = {sig: signal.signal(sig, self._on_signal) for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
        try:
            while True:
                status = self._wait_for_exit(self.poll)
                if status is not None:
                    return self._verdict(status)
                hang = self._check_hang()
                if hang:
                    self._kill()
                    return EXIT_HANG, hang, "raise --call-timeout if the model needs longer (0 waits forever)"
                if self.interrupted_at is not None and time.monotonic() - self.interrupted_at > INTERRUPT_GRACE:
                    self._kill()  # stuck inside the FMU: it cannot see the interrupt
                    return self._stopped()
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
            if self.pidfd is not None:
                os.close(self.pidfd)

    def _on_signal(self, signum, frame) -> None:
        # The first Ctrl-C or termination lets the worker stop as on an error, within the grace (an
        # interrupted --force puts the old outputs back); a second one stops it now.
        if self.interrupted_at is None:
            self.interrupted_at = time.monotonic()
            self.terminated = signum != signal.SIGINT
            _send(self.pid, signal.SIGINT)
        else:
            self.terminated = self.terminated or signum != signal.SIGINT
            self.interrupted_at = -math.inf

    def _wait_for_exit(self, timeout: float):
        if self.pidfd is not None:
            with contextlib.suppress(InterruptedError):
                select.select([self.pidfd], [], [], timeout)
        else:
            time.sleep(timeout)
        try:
            pid, status = os.waitpid(self.pid, os.WNOHANG)
        except ChildProcessError:
            return 0
        return status if pid else None

    def _check_hang(self) -> str | None:
        if self.call_timeout <= 0:
            return None
        return self.worker.check_hang(self.call_timeout) or (self.helper and self.helper.check_hang(self.call_timeout))

    def _kill(self) -> None:
        # the worker first: killed after its helper, it may still run long enough to see the helper
        # gone and start reporting that (a traceback line beside the supervisor's one line)
        _send(self.pid, signal.SIGKILL)
        _stop_helper()
        with contextlib.suppress(ChildProcessError):
            os.waitpid(self.pid, 0)

    def _stopped(self) -> tuple[int, str, str]:
        return (EXIT_TERMINATED, "terminated", "") if self.terminated else (EXIT_INTERRUPTED, "interrupted", "")

    def _verdict(self, status: int) -> tuple[int, str, str]:
        reported = CALL[REPORT_SLOT]
        stopped = os.WIFSIGNALED(status) or os.WEXITSTATUS(status) == EXIT_INTERRUPTED
        if self.interrupted_at is not None and stopped:  # the worker leaves this line to us
            return self._stopped()
        if self.terminated:     # it finished or failed (and said so) before it saw the signal
            return EXIT_TERMINATED, "", ""
        if os.WIFSIGNALED(status):
            sig = os.WTERMSIG(status)
            return 128 + sig, *breadcrumb.crash_message(f"crashed ({signal.Signals(sig).name})")
        code = os.WEXITSTATUS(status)
        if reported >= REPORTED:
            return code, "", ""  # the worker printed its own messages
        return code or EXIT_UNEXPECTED, *breadcrumb.crash_message(f"ended the process (exit code {code})")


class _Watch:
    """The calls of one process, the worker or its helper: it is stuck in an FMI call when the
    call is in progress and the process has not run any Python code (its SIGUSR1 handler) for
    call_timeout seconds."""

    def __init__(self, calls, pid, helper: bool):
        self.calls, self.pid, self.helper = calls, pid, helper
        self.ping_sent: float | None = None

    def check_hang(self, call_timeout: float) -> str | None:
        function, in_call, t = breadcrumb.last_call(self.helper)
        pid, now = self.pid(), time.monotonic()
        if not in_call or not _running(pid):
            self.ping_sent = None    # a helper that ended is reported by the worker, which reaps it
        elif self.ping_sent is None or self.calls[PING_SLOT] == 0:
            self.calls[PING_SLOT] = 1
            self.ping_sent = now
            _send(pid, signal.SIGUSR1)
        elif now - self.ping_sent >= call_timeout:
            return (f"{breadcrumb.who(self.helper)} did not return from {function}{breadcrumb.at(t)} within "
                    f"{call_timeout:g} s and was stopped")
        return None


def _running(pid: int) -> bool:
    """Alive and not yet a zombie (a helper's parent reaps it only when it asks for its result)."""
    if not pid:
        return False
    try:
        with open(f"/proc/{pid}/stat", "rb") as stat:
            return stat.read().rsplit(b")", 1)[1].split()[0] not in (b"Z", b"X")
    except (OSError, IndexError):
        return True     # no /proc: taken as alive


def _stop_helper() -> None:
    if HELPER is not None and HELPER[PID_SLOT]:
        _send(HELPER[PID_SLOT], signal.SIGKILL)


def _send(pid: int, sig: int) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, sig)


def _open_pidfd(pid: int):
    try:
        return os.pidfd_open(pid)
    except (AttributeError, OSError):
        return None


# -- outputs -------------------------------------------------------------------------------

def _declared_outputs(args) -> list[Path]:
    from ..errors import FmuBuilderError
    plan = getattr(args, "plan", None)
    try:
        return plan(args).paths() if plan else []
    except FmuBuilderError:     # the worker reports it, before any work
        return []


def _fingerprint(path: Path):
    try:
        stat = path.stat()
    except OSError:
        return None
    return stat.st_mtime_ns, stat.st_size
