"""An FMU binary that segfaults, aborts, calls exit() or hangs cannot take the tool down:
every command ends with a non-zero exit and one `error:` line naming the FMI call, leaves no
temporary folder and writes no output.

The FMUs are the bouncing ball with a misbehaving binary (tests/fmi/crashing/crash_model.c);
the data are the healthy bouncing ball's, simulated by fmubuilder.
"""
import os
import shutil
import signal
import subprocess
import sys
import time

import pytest

from tests.fmi.crash_fmus import MODES, crash_fmus

CALL_TIMEOUT = "1"  # seconds, for the hanging binary
EXPECTED_EXIT = {"segfault": 128 + signal.SIGSEGV, "abort": 128 + signal.SIGABRT, "exit0": 3, "exit3": 3,
                 "hang": 124, "instantiate_segfault": 128 + signal.SIGSEGV}


@pytest.fixture(scope="module")
def fmus():
    return crash_fmus()


@pytest.fixture(scope="module")
def data_csv(tmp_path_factory, bouncing_ball_fmu):
    from fmubuilder.simulation import simulate
    path = tmp_path_factory.mktemp("data") / "ball.csv"
    simulate(bouncing_ball_fmu, stop_time=1.0, variables=["h", "v"], solver="euler", step_size=1e-3,
             output_interval=0.01).to_csv(path)
    return path


def run_cli(*args, tmpdir, cwd):
    env = {**os.environ, "TMPDIR": str(tmpdir)}
    return subprocess.run([sys.executable, "-m", "fmubuilder.cli", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, env=env, timeout=120)


def command_line(command, fmu, data, out):
    test = data.with_name(f"test_{data.name}")     # data have one role each
    if not test.exists():
        shutil.copyfile(data, test)
    return {
        "simulate": ["simulate", fmu, "--stop-time", "1", "-o", out / "result.csv"],
        "diagnose": ["diagnose", fmu, "--data", data, "--json", out / "diagnosis.json", "--plots", out / "plots",
                     "--time-budget", "10"],
        "train": ["train", fmu, "--data", data, "--target", "der(v)", "--inputs", "h,v", "--epochs", "1",
                  "--element-length", "1", "--step-size", "0.01", "--quiet", "-o", out / "trained.nfmu",
                  "--json", out / "metrics.json"],
        "hybridize": ["hybridize", fmu, "--train", data, "--test", test, "-o", out / "hybrid.fmu",
                      "--report", out / "report", "--time-budget", "10"],
    }[command]


def assert_clean_failure(proc, mode, tmpdir, out):
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert "Traceback" not in proc.stderr
    assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    function = "fmi2Instantiate" if mode == "instantiate_segfault" else "fmi2GetDerivatives"
    assert function in lines[0], lines[0]
    if mode == "hang":
        assert f"did not return from {function}" in lines[0] and "--call-timeout" in lines[0]
    else:
        assert "at t = 0.5" in lines[0] or function == "fmi2Instantiate", lines[0]
        assert "nothing was written" in lines[0]
    assert proc.returncode == EXPECTED_EXIT[mode], (proc.returncode, proc.stderr)
    assert list(tmpdir.iterdir()) == [], "temporary folders left behind"
    assert list(out.iterdir()) == [], "outputs of the failed run left behind"


@pytest.mark.parametrize("command", ["simulate", "diagnose", "train", "hybridize"])
@pytest.mark.parametrize("mode", MODES)
def test_a_misbehaving_binary_ends_the_command_in_one_line(fmus, data_csv, tmp_path, mode, command):
    tmpdir, out = tmp_path / "tmp", tmp_path / "out"
    tmpdir.mkdir()
    out.mkdir()
    proc = run_cli(*command_line(command, fmus[mode], data_csv, out), "--call-timeout", CALL_TIMEOUT,
                   tmpdir=tmpdir, cwd=tmp_path)
    assert_clean_failure(proc, mode, tmpdir, out)


@pytest.fixture(scope="module")
def crashing_hybrids(tmp_path_factory, fmus):
    """Hybrid FMUs exported (by the CLI) around two misbehaving originals: export does not run
    the original's binary, so it succeeds; validate runs it through fmpy."""
    from fmubuilder.fmi import read_model_info
    from fmubuilder.hybridize.terms import spec_from_fitted_term
    folder = tmp_path_factory.mktemp("hybrids")
    fitted = {"channel": "der(v)", "terms": [{"variable": "v", "basis": "w", "center": 0.0, "coefficient": -0.4}]}
    hybrids = {}
    for mode in ("segfault", "hang"):
        (folder / mode).mkdir()
        spec = spec_from_fitted_term(fitted, fmus[mode], read_model_info(fmus[mode]).guid, folder / mode)
        spec_path = spec.save(folder / f"{mode}.json")
        proc = run_cli("export", spec_path, "-o", folder / f"{mode}.fmu", tmpdir=folder, cwd=folder)
        assert proc.returncode == 0, proc.stderr
        hybrids[mode] = folder / f"{mode}.fmu"
    return hybrids


@pytest.mark.parametrize("mode", ["segfault", "hang"])
def test_validate_of_a_hybrid_around_a_misbehaving_binary(crashing_hybrids, tmp_path, mode):
    tmpdir, out = tmp_path / "tmp", tmp_path / "out"
    tmpdir.mkdir()
    out.mkdir()
    proc = run_cli("validate", crashing_hybrids[mode], "--stop-time", "1", "--call-timeout", CALL_TIMEOUT,
                   tmpdir=tmpdir, cwd=tmp_path)
    assert_clean_failure(proc, mode, tmpdir, out)


def test_ctrl_c_during_a_hanging_call_stops_cleanly(fmus, tmp_path):
    """The worker cannot see an interrupt while the binary hangs: the parent stops it after a grace period."""
    tmpdir, out = tmp_path / "tmp", tmp_path / "out"
    tmpdir.mkdir()
    out.mkdir()
    env = {**os.environ, "TMPDIR": str(tmpdir)}
    proc = subprocess.Popen([sys.executable, "-m", "fmubuilder.cli", "simulate", str(fmus["hang"]), "--stop-time", "1",
                             "--call-timeout", "0", "-o", str(out / "result.csv")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.monotonic() + 60
    while not any(tmpdir.iterdir()) and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(1.0)  # well inside the hanging call by now
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 130
    assert stderr.strip().splitlines() == ["error: interrupted; nothing was written"]
    assert list(tmpdir.iterdir()) == [] and list(out.iterdir()) == []


def test_ctrl_c_in_python_code_stops_cleanly(bouncing_ball_fmu, tmp_path):
    tmpdir, out = tmp_path / "tmp", tmp_path / "out"
    tmpdir.mkdir()
    out.mkdir()
    env = {**os.environ, "TMPDIR": str(tmpdir)}
    proc = subprocess.Popen([sys.executable, "-m", "fmubuilder.cli", "simulate", str(bouncing_ball_fmu),
                             "--stop-time", "1e5", "--solver", "euler", "--step-size", "1e-3", "--output-interval", "10",
                             "-o", str(out / "result.csv")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.monotonic() + 60
    while not any(tmpdir.iterdir()) and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 130
    assert stderr.strip().splitlines() == ["error: interrupted; nothing was written"]
    assert list(tmpdir.iterdir()) == [] and list(out.iterdir()) == []


def _worker_of(pid: int) -> int:
    children = open(f"/proc/{pid}/task/{pid}/children").read().split()
    return int(children[0])


@pytest.mark.parametrize("ending", ["success", "error", "SIGTERM", "worker killed"])
def test_no_temporary_folder_is_left_on_any_exit_path(bouncing_ball_fmu, tmp_path, ending):
    tmpdir, out = tmp_path / "tmp", tmp_path / "out"
    tmpdir.mkdir()
    out.mkdir()
    before = sorted(tmpdir.iterdir())
    long_run = ["--stop-time", "1e5", "--solver", "euler", "--step-size", "1e-3", "--output-interval", "10"]
    args = {"success": ["--stop-time", "1"], "error": ["--start", "h=high"]}.get(ending, long_run)
    env = {**os.environ, "TMPDIR": str(tmpdir)}
    proc = subprocess.Popen([sys.executable, "-m", "fmubuilder.cli", "simulate", str(bouncing_ball_fmu), *args,
                             "-o", str(out / "result.csv")], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env)
    if ending in ("SIGTERM", "worker killed"):
        deadline = time.monotonic() + 60
        while not any(tmpdir.iterdir()) and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(1.0)
        if ending == "SIGTERM":
            proc.send_signal(signal.SIGTERM)
        else:
            os.kill(_worker_of(proc.pid), signal.SIGKILL)
    _, stderr = proc.communicate(timeout=60)
    assert sorted(tmpdir.iterdir()) == before
    if ending == "success":
        assert proc.returncode == 0 and (out / "result.csv").is_file()
        return
    assert proc.returncode != 0 and len(stderr.strip().splitlines()) == 1, stderr
    assert list(out.iterdir()) == []
    if ending == "worker killed":
        assert "crashed (SIGKILL)" in stderr  # inside an FMI call or between calls, as it happened
