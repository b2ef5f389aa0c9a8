"""Bad input gets a one-line error naming the problem, a non-zero exit and no traceback."""
import subprocess
import sys

import pytest

from tests.fmi.broken_fmus import co_simulation_only, rewrite_fmu, set_fmi_version


def run_cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "fmubuilder.cli", *map(str, args)],
                          capture_output=True, text=True, cwd=cwd, timeout=300)


def assert_one_line_error(proc, *fragments):
    assert proc.returncode != 0
    assert "Traceback" not in proc.stderr
    lines = [line for line in proc.stderr.strip().splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("error: ")
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


@pytest.fixture
def broken(tmp_path, bouncing_ball_fmu):
    def make(name, **kwargs):
        return rewrite_fmu(bouncing_ball_fmu, tmp_path / name, **kwargs)
    return make


@pytest.mark.parametrize("command", ["inspect", "simulate"])
def test_not_a_zip(tmp_path, command):
    path = tmp_path / "model.fmu"
    path.write_text("this is not an FMU")
    assert_one_line_error(run_cli(command, path), "not a zip archive")


def test_missing_file(tmp_path):
    assert_one_line_error(run_cli("inspect", tmp_path / "nothing.fmu"), "no such file")


def test_no_model_description(broken):
    assert_one_line_error(run_cli("inspect", broken("x.fmu", drop=("modelDescription.xml",))), "no modelDescription.xml")


@pytest.mark.parametrize("version", ["1.0", "3.0"])
def test_wrong_fmi_version(broken, version):
    path = broken(f"v{version}.fmu", xml=set_fmi_version(version))
    assert_one_line_error(run_cli("inspect", path), f"FMI {version}", "FMI 2.0")


def test_co_simulation_only(broken):
    assert_one_line_error(run_cli("inspect", broken("cs.fmu", xml=co_simulation_only)), "Co-Simulation only", "Model Exchange")


def test_no_linux64_binary(broken):
    assert_one_line_error(run_cli("inspect", broken("nobin.fmu", drop=("binaries/linux64", "sources/"))), "no linux64 binary")


def test_corrupt_model_description(broken):
    path = broken("corrupt.fmu", xml=lambda text: text[: len(text) // 2])
    assert_one_line_error(run_cli("inspect", path), "cannot read modelDescription.xml")


def test_unknown_variable(bouncing_ball_fmu):
    proc = run_cli("simulate", bouncing_ball_fmu, "--variables", "h,heigth")
    assert_one_line_error(proc, "unknown variable 'heigth'")


def test_unknown_start_name(bouncing_ball_fmu):
    assert_one_line_error(run_cli("simulate", bouncing_ball_fmu, "--start", "gg=3"), "unknown variable 'gg'")


@pytest.mark.parametrize("item", ["h", "h=", "=3"])
def test_malformed_start(bouncing_ball_fmu, item):
    assert_one_line_error(run_cli("simulate", bouncing_ball_fmu, "--start", item), "malformed --start")


def test_start_value_of_wrong_type(bouncing_ball_fmu):
    assert_one_line_error(run_cli("simulate", bouncing_ball_fmu, "--start", "h=high"), "cannot set h")


def test_stop_before_start(bouncing_ball_fmu):
    assert_one_line_error(run_cli("simulate", bouncing_ball_fmu, "--start-time", "2", "--stop-time", "1"), "stop time")


def test_output_not_clobbered(tmp_path, bouncing_ball_fmu):
    out = tmp_path / "result.csv"
    out.write_text("precious")
    assert_one_line_error(run_cli("simulate", bouncing_ball_fmu, "-o", out), "--force")
    assert out.read_text() == "precious"


def test_inspect_lists_states_and_capabilities(bouncing_ball_fmu):
    proc = run_cli("inspect", bouncing_ball_fmu)
    assert proc.returncode == 0, proc.stderr
    for text in ("der(h)", "der(v)", "event indicators", "directional derivatives", "default experiment"):
        assert text in proc.stdout


def test_help_and_inspect_do_not_import_heavy_packages(bouncing_ball_fmu):
    """`fmubuilder --help` and `inspect` must start fast: no torch, onnx or scipy."""
    code = ("import sys; from fmubuilder.cli import build_parser; from fmubuilder.inspect_fmu import describe; "
            f"build_parser(); describe({str(bouncing_ball_fmu)!r}); "
            "print(sorted(m for m in ('torch', 'onnx', 'onnxruntime', 'scipy', 'matplotlib') if m in sys.modules))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[]"


def test_numeric_warnings_are_folded_into_the_one_line_error(tmp_path, bouncing_ball_fmu):
    """Values near 1e300 overflow in the diagnosis: numpy's warnings must not spill onto the terminal."""
    from fmubuilder.simulation import simulate
    result = simulate(bouncing_ball_fmu, stop_time=1.0, variables=["h", "v"], solver="euler", step_size=1e-3,
                      output_interval=0.01)
    huge = tmp_path / "huge.csv"
    huge.write_text("time,h,v\n" + "".join(f"{t!r},{h * 1e300!r},{v * 1e300!r}\n"
                                           for t, h, v in zip(result.time.tolist(), result["h"].tolist(), result["v"].tolist())))
    test = tmp_path / "huge_test.csv"
    test.write_bytes(huge.read_bytes())
    proc = run_cli("hybridize", bouncing_ball_fmu, "--train", huge, "--test", test, "-o", tmp_path / "h.fmu",
                   "--report", tmp_path / "report", "--time-budget", "10")
    assert_one_line_error(proc, "overflow")
    assert not (tmp_path / "report").exists() and not (tmp_path / "h.fmu").exists()


def test_every_command_prints_its_help():
    """argparse formats each help text with %-interpolation: a stray '%' crashes `--help`."""
    import argparse
    from fmubuilder.cli import build_parser
    parser = build_parser()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    assert len(commands) >= 10
    for name, command in commands.items():
        assert name in command.format_help(), name
