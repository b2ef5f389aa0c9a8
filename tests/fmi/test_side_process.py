"""Work in a helper process beside the caller (fmi/side_process.py): its value or its error comes
back; an FMU that crashes in the helper is reported with the call it crashed in; the command
line's supervisor stops a helper stuck in a call as it stops the worker.

The misbehaving FMUs are the bouncing ball whose binary crashes or hangs in fmi2GetDerivatives at
t = 0.5 s (tests/fmi/crashing/crash_model.c).
"""
import faulthandler
import os
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import pytest

from fmubuilder.errors import FmuBuilderError
from fmubuilder.fmi import breadcrumb
from fmubuilder.fmi.instance import Fmu
from fmubuilder.fmi.side_process import SideProcess, can_run_beside
from tests.fmi.crash_fmus import crash_fmus

pytestmark = pytest.mark.skipif(not can_run_beside(), reason="no helper process on this platform")


def simulate_to_one_second(fmu):
    from fmubuilder.simulation import simulate
    result = simulate(fmu, stop_time=1.0, variables=["h"], solver="euler", step_size=1e-3, output_interval=0.1)
    return float(result["h"][-1])


def pid_and_square(x):
    return os.getpid(), x * x


def test_the_work_runs_in_another_process_and_returns_its_value():
    with SideProcess("squaring", pid_and_square, (7,)) as side:
        pid, value = side.result()
    assert pid != os.getpid() and value == 49
    assert SideProcess("squaring", pid_and_square, (7,), in_caller=True).result() == (os.getpid(), 49)


def test_the_ball_simulated_beside_equals_the_ball_simulated_here(bouncing_ball_fmu):
    with SideProcess("simulating", simulate_to_one_second, (bouncing_ball_fmu,)) as side:
        here = simulate_to_one_second(bouncing_ball_fmu)    # the caller works meanwhile
        assert side.result() == here


def fails_with(exception):
    raise exception


def test_an_error_in_the_helper_is_raised_by_result():
    with SideProcess("failing", fails_with, (FmuBuilderError("the data have NaN in 'speed': remove them"),)) as side:
        with pytest.raises(FmuBuilderError, match="NaN in 'speed'"):
            side.result()
    with SideProcess("failing", fails_with, (ZeroDivisionError("division by zero"),)) as side:
        with pytest.raises(ZeroDivisionError) as raised:
            side.result()
    assert "in the helper process" in raised.value.__notes__[0] and "fails_with" in raised.value.__notes__[0]


def test_a_helper_without_its_own_crumb_page_says_so_and_does_no_work(monkeypatch):
    def cannot_map():
        raise OSError(12, "cannot map the helper's breadcrumb page")
    monkeypatch.setattr(breadcrumb, "become_helper", cannot_map)     # the forked helper inherits it
    with SideProcess("squaring", pid_and_square, (7,)) as side:
        with pytest.raises(FmuBuilderError, match=r"cannot keep its own record of FMI calls .*--jobs 1"):
            side.result()


def crash_quietly(fmu):
    faulthandler.disable()      # pytest's, inherited: it would dump the helper's stack into the output
    return simulate_to_one_second(fmu)


def test_a_crash_inside_the_fmu_names_the_call_and_leaves_the_callers_crumbs_alone():
    before = breadcrumb.last_call()
    with SideProcess("training the NeuralFMU", crash_quietly, (crash_fmus()["segfault"],)) as side:
        with pytest.raises(FmuBuilderError) as raised:
            side.result()
    message = str(raised.value)
    assert "crashed (SIGSEGV) in fmi2GetDerivatives at t = 0.5" in message, message
    assert "(training the NeuralFMU)" in message and "report it to its vendor" in message
    assert breadcrumb.last_call() == pytest.approx(before, nan_ok=True)     # (no call yet: nan)
    assert breadcrumb.last_call(helper=True) == ("", False, pytest.approx(float("nan"), nan_ok=True))


KEPT = []       # the helper's FMUs kept open


def open_and_keep(fmu):
    """An FMU extracted and never closed, as a cache would keep it: the removal at exit never runs."""
    KEPT.append(Fmu(fmu))
    return str(KEPT[-1].archive.directory)


@pytest.mark.parametrize("ending", ["returned", "crashed in the FMU"])
def test_the_helper_leaves_no_temporary_files(bouncing_ball_fmu, tmp_path, monkeypatch, ending):
    temp = tmp_path / "tmp"
    temp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(temp))
    if ending == "returned":
        with SideProcess("keeping an FMU", open_and_keep, (bouncing_ball_fmu,)) as side:
            extracted = Path(side.result())
        assert extracted.is_relative_to(temp) and extracted.name.startswith("fmubuilder-bouncing_ball-")
    else:
        with SideProcess("crashing", crash_quietly, (crash_fmus()["segfault"],)) as side:
            with pytest.raises(FmuBuilderError, match="SIGSEGV"):
                side.result()
    assert list(temp.iterdir()) == []


def test_a_helper_that_cannot_start_leaves_nothing_open(tmp_path, monkeypatch):
    temp = tmp_path / "tmp"
    temp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(temp))
    descriptors = sorted(os.listdir("/proc/self/fd"))

    def no_fork():
        raise BlockingIOError(11, "Resource temporarily unavailable")
    monkeypatch.setattr(os, "fork", no_fork)
    with pytest.raises(BlockingIOError):
        SideProcess("squaring", pid_and_square, (3,))
    assert list(temp.iterdir()) == [] and sorted(os.listdir("/proc/self/fd")) == descriptors
    assert can_run_beside()         # no helper counts as running


def test_leaving_the_block_early_stops_the_helper():
    with pytest.raises(RuntimeError):
        with SideProcess("sleeping", time.sleep, (600,)) as side:
            pid = side.pid
            raise RuntimeError("the caller failed")
    assert not running(pid)


def a_megabyte():
    return bytes(1 << 20)       # more than a pipe holds: the helper waits in its write for the caller


def test_leaving_early_while_the_helper_waits_to_send_a_large_result_keeps_the_callers_exception():
    with pytest.raises(KeyboardInterrupt):
        with SideProcess("sending", a_megabyte) as side:
            pid = side.pid
            time.sleep(0.5)
            raise KeyboardInterrupt
    assert not running(pid)


def interrupt(signum, frame):
    raise KeyboardInterrupt


def test_an_interrupt_while_waiting_for_the_result_stops_the_helper():
    previous = signal.signal(signal.SIGALRM, interrupt)
    try:
        side = SideProcess("sleeping", time.sleep, (600,))
        pid = side.pid
        signal.alarm(1)
        with pytest.raises(KeyboardInterrupt):
            side.result()
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    assert not running(pid)
    assert SideProcess("squaring", pid_and_square, (3,)).result()[1] == 9     # a next helper can start


SUPERVISED = textwrap.dedent("""
    import argparse, os, sys
    from fmubuilder.cli.supervise import run_supervised
    from fmubuilder.fmi.side_process import SideProcess
    from tests.fmi.test_side_process import simulate_to_one_second

    def execute(args):
        with SideProcess("simulating the hanging ball", simulate_to_one_second, (sys.argv[1],)) as side:
            print("helper", side.pid, flush=True)
            for _ in range(3):                        # the worker's own calls go on meanwhile
                simulate_to_one_second(sys.argv[2])
            side.result()
        return 0

    sys.exit(run_supervised(argparse.Namespace(call_timeout=1.0), execute))
""")


def test_the_supervisor_stops_a_helper_stuck_in_a_call_and_the_worker_with_it(bouncing_ball_fmu, tmp_path):
    proc = subprocess.run([sys.executable, "-c", SUPERVISED, str(crash_fmus()["hang"]), str(bouncing_ball_fmu)],
                          capture_output=True, text=True, timeout=120, cwd=os.getcwd(),
                          env={**os.environ, "TMPDIR": str(tmp_path)})
    assert proc.returncode == 124, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "did not return from fmi2GetDerivatives at t = 0.5 s within 1 s" in lines[0], lines
    helper = int(proc.stdout.split()[1])
    assert not running(helper)


def running(pid: int) -> bool:
    """Alive, not a zombie (an orphan's zombie waits for a reaper that a container may not have)."""
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            state = open(f"/proc/{pid}/stat", "rb").read().rsplit(b")", 1)[1].split()[0]
        except FileNotFoundError:
            return False
        if state in (b"Z", b"X"):
            return False
        time.sleep(0.05)    # the kill may not have landed yet
    return True
