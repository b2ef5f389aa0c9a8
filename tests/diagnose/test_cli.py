"""`fmubuilder diagnose` on the command line: the printed table, the JSON report, the plots and
one-line errors for bad input."""
import argparse
import json

import pytest

from fmubuilder.build import example_fmu
from fmubuilder.cli.diagnose import add_diagnose_parser
from fmubuilder.errors import FmuBuilderError

from .conftest import DC_DRIVE_BENCH, measure

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _run(argv):
    parser = argparse.ArgumentParser(prog="fmubuilder")
    add_diagnose_parser(parser.add_subparsers())
    args = parser.parse_args(["diagnose", *argv])
    args.func(args)


@pytest.fixture(scope="module")
def heating_data(data_dir):
    folder = data_dir / "cli"
    folder.mkdir()
    return measure(folder, "dc_drive_truth_extra_heating", stop_time=8.0, bench=DC_DRIVE_BENCH)


def test_diagnose_prints_the_errors_and_writes_json_and_plots(heating_data, tmp_path, capsys):
    report, plots = tmp_path / "diagnosis.json", tmp_path / "plots"
    _run([str(example_fmu("dc_drive")), "--data", str(heating_data), "--json", str(report), "--plots", str(plots)])
    out = capsys.readouterr().out
    assert "signal" in out and "temperature" in out and "Significant effect" in out
    assert "Traced to der(temperature)" in out
    data = json.loads(report.read_text())
    assert data["channel"] == "der(temperature)"
    assert {e["signal"] for e in data["errors"]} == set(DC_DRIVE_BENCH["signals"])
    assert data["candidates"][0]["channel"] == "der(temperature)"
    for name in ("signals.png", "residuals.png", "residual_vs_inputs.png"):
        assert (plots / name).read_bytes().startswith(PNG_SIGNATURE)


def test_an_existing_json_file_needs_force(heating_data, tmp_path):
    report = tmp_path / "diagnosis.json"
    report.write_text("{}")
    with pytest.raises(FmuBuilderError, match="--force"):
        _run([str(example_fmu("dc_drive")), "--data", str(heating_data), "--json", str(report)])


def test_a_column_that_is_no_model_variable_is_a_one_line_error(tmp_path):
    data = tmp_path / "data.csv"
    data.write_text("time,sped\n" + "".join(f"{0.1 * k:.1f},{k}\n" for k in range(20)))
    with pytest.raises(FmuBuilderError) as error:
        _run([str(example_fmu("dc_drive")), "--data", str(data)])
    message = str(error.value)
    assert "sped" in message and "speed" in message and "\n" not in message


def test_a_negative_time_budget_is_rejected(heating_data):
    with pytest.raises(FmuBuilderError, match="time-budget"):
        _run([str(example_fmu("dc_drive")), "--data", str(heating_data), "--time-budget", "-1"])


def test_diagnose_calls_ar1_sensor_noise_without_an_effect_no_effect(data_dir, capsys):
    """The declared DC drive's own data with sensor noise correlated between samples (AR(1),
    rho 0.7, the variance of the white default): noise, not an effect."""
    folder = data_dir / "cli_ar1"
    folder.mkdir()
    bench = {**DC_DRIVE_BENCH, "noise_model": "ar1", "noise_rho": 0.7}
    data = measure(folder, "dc_drive", stop_time=15.0, bench=bench, seed=3)
    _run([str(example_fmu("dc_drive")), "--data", str(data)])
    out = capsys.readouterr().out
    assert "No significant effect" in out and "Significant effect" not in out
