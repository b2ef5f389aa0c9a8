"""Run one piece of work in a forked helper process while the caller goes on with its own.

`hybridize` trains the NeuralFMU this way beside the other candidates, on a second core. The
work runs exactly as it would in the caller (same code, same data, its own FMU instances); its
return value, or its exception, comes back pickled through a pipe when the caller asks for it.

The helper leaves its FMI breadcrumbs on a page of its own (breadcrumb.py), which the command
line's supervisor watches as it watches the worker's: a call that never returns stops both, and
a helper that crashes inside the FMU's binary is reported by `result()` with the call it was in.
The helper's temporary files (the FMUs it extracts) go to a folder the caller makes and removes
when the helper has ended, however it ended: a helper leaves by os._exit, which skips the removal
at exit, or by a crash or a kill, which skips everything.
One helper at a time; where none can run (no fork, no helper page, one already running), or the
caller asks for it (in_caller), the work runs in the caller when started.
"""
from __future__ import annotations

import contextlib
import os
import pickle
import shutil
import signal
import sys
import tempfile
import traceback

from ..errors import FmuBuilderError
from . import breadcrumb
from .breadcrumb import HELPER, PID_SLOT

_active: SideProcess | None = None     # the helper running now


def cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def can_run_beside() -> bool:
    return hasattr(os, "fork") and breadcrumb.has_helper_page() and _active is None


class SideProcess:
    """`function(*args, **kwargs)` in a helper process; `result()` waits for it. As a context
    manager, leaving the block before `result()` (an error in the caller) stops the helper.
    label says what the helper does, for its error messages. in_caller: run the function here and
    now instead (as when no helper can run), its exception raised at once."""

    def __init__(self, label: str, function, args=(), kwargs=None, in_caller: bool = False):
        self.label = label
        self.pid = None
        self._scratch = None
        self._inline = None
        if in_caller or not can_run_beside():
            self._inline = True, function(*args, **(kwargs or {}))
        else:
            self._start(function, args, kwargs or {})

    def _start(self, function, args, kwargs) -> None:
        global _active
        sys.stdout.flush()
        sys.stderr.flush()
        read, write = os.pipe()
        scratch = None
        try:
            scratch = tempfile.mkdtemp(prefix="fmubuilder-helper-")
            pid = os.fork()
        except OSError:     # no process to hand them to
            os.close(read)
            os.close(write)
            if scratch is not None:
                shutil.rmtree(scratch, ignore_errors=True)
            raise
        if pid == 0:
            os.close(read)
            os.environ["TMPDIR"] = tempfile.tempdir = scratch   # for the helper and the tools it starts
            _helper_main(write, function, args, kwargs)
        os.close(write)
        self._scratch = scratch
        self.pid, self._pipe = pid, read
        HELPER[PID_SLOT] = pid
        _active = self

    def result(self):
        """The work's return value; its exception re-raised here."""
        ok, value = self._inline if self._inline is not None else self._collect()
        if ok:
            return value
        raise value

    def _collect(self) -> tuple[bool, object]:
        global _active
        status = None
        try:
            payload = _read_all(self._pipe)
            _, status = os.waitpid(self.pid, 0)
            # only a helper that ended by itself sent all of it: one killed while it wrote (stopped
            # by stop() with a result larger than the pipe holds) left a part that does not unpickle
            if payload and os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0:
                return pickle.loads(payload)
            return False, FmuBuilderError(self._ended(status))
        finally:
            if status is None:      # interrupted while waiting: the helper must not outlive it
                with contextlib.suppress(ProcessLookupError, ChildProcessError):
                    os.kill(self.pid, signal.SIGKILL)
                    os.waitpid(self.pid, 0)
            os.close(self._pipe)
            shutil.rmtree(self._scratch, ignore_errors=True)
            self.pid = self._scratch = None
            _active = None
            HELPER[PID_SLOT] = 0
            breadcrumb.reset_helper()

    def _ended(self, status: int) -> str:
        if os.WIFSIGNALED(status):
            what = f"crashed ({signal.Signals(os.WTERMSIG(status)).name})"
        else:
            what = f"ended the process (exit code {os.WEXITSTATUS(status)})"
        message, hint = breadcrumb.crash_message(what, helper=True)
        return f"{message} ({self.label}); {hint}"

    def stop(self) -> None:
        """Stop a helper whose result is no longer wanted."""
        if self.pid is not None:
            os.kill(self.pid, signal.SIGKILL)
            self._collect()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def _helper_main(write: int, function, args, kwargs) -> None:
    """The helper's whole life: it never returns into the caller's code."""
    code = 0
    try:
        try:
            breadcrumb.become_helper()
        except OSError as exc:      # without its own page a crash would be blamed on the caller's call
            outcome = False, FmuBuilderError(f"the second process cannot keep its own record of FMI calls ({exc}); "
                                             "--jobs 1 does the work in one process")
        else:
            outcome = _outcome(function, args, kwargs)
        payload = _picklable(*outcome)
        view = memoryview(payload)
        while view:
            view = view[os.write(write, view):]
    except BaseException:           # noqa: BLE001 - interrupted, or the pipe closed: the caller reports
        code = 1
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:       # noqa: BLE001
                pass
        os._exit(code)


def _outcome(function, args, kwargs) -> tuple[bool, object]:
    try:
        return True, function(*args, **kwargs)
    except Exception as exc:        # noqa: BLE001 - handed to the caller
        if not isinstance(exc, FmuBuilderError):   # a bug: keep where it happened for --debug
            exc.add_note("in the helper process:\n" + "".join(traceback.format_exception(exc)))
        return False, exc


def _picklable(ok: bool, value) -> bytes:
    """The outcome pickled, or the exception's message when it (or the result) cannot cross over."""
    try:
        payload = pickle.dumps((ok, value))
        pickle.loads(payload)       # exceptions with their own __init__ may not load back
        return payload
    except Exception as exc:        # noqa: BLE001
        message = str(value) if not ok else f"its result cannot be sent ({exc})"
        return pickle.dumps((False, FmuBuilderError(message)))


def _read_all(fd: int) -> bytes:
    chunks = []
    while chunk := os.read(fd, 1 << 20):
        chunks.append(chunk)
    return b"".join(chunks)
