"""The one data module: CSV checks, sidecars (start values, declared sensor lag), the sensor model."""
import json
import re

import numpy as np
import pytest

from fmubuilder.build import example_fmu
from fmubuilder.data import first_order_lag, load_data, sidecar_path
from fmubuilder.errors import FmuBuilderError
from fmubuilder.fmi import read_model_info


@pytest.fixture(scope="module")
def info():
    return read_model_info(example_fmu("dc_drive"))


def write(tmp_path, text, sidecar=None, name="data.csv"):
    path = tmp_path / name
    path.write_text(text)
    if sidecar is not None:
        sidecar_path(path).write_text(sidecar if isinstance(sidecar, str) else json.dumps(sidecar))
    return path


ROWS = "time,speed,speed_std\n" + "".join(f"{0.1 * k:.1f},{k},{0.5}\n" for k in range(20))


def test_signals_spread_and_sidecar(info, tmp_path):
    path = write(tmp_path, ROWS, {"start_values": {"J": 0.02}, "bench": {"lag": 0.1, "runs": 3}})
    data = load_data(path, info)
    assert data.names == ["speed"] and set(data.std) == {"speed"}
    assert data.start_values == {"J": 0.02}
    assert data.sensor_lag == 0.1 and data.runs == 3 and data.path == path
    np.testing.assert_array_equal(data.window(0.5, 0.9).time, data.time[5:10])


def test_a_declared_sensor_lag_wins_and_no_sidecar_means_no_lag(info, tmp_path):
    declared = write(tmp_path, ROWS, {"sensor_lag": 0.25, "bench": {"lag": 0.1}}, name="a.csv")
    assert load_data(declared, info).sensor_lag == 0.25
    plain = write(tmp_path, ROWS, name="b.csv")
    data = load_data(plain, info)
    assert data.sensor_lag == 0.0 and data.start_values == {}


@pytest.mark.parametrize("text, sidecar, fragment", [
    (ROWS, {"sensor_lag": -1}, "sensor lag"),
    (ROWS, "{not json", "not valid JSON"),
    ("time,sped\n0,1\n1,2\n", None, "sped"),
    ("time,speed\n0,1\n1,nan\n", None, "not a finite number"),
    ("time,speed\n0,1\n", None, "at least 2"),
    ("time,speed\n0,1e300\n1,2e300\n", None, "up to 2e\\+300.*overflow"),
])
def test_bad_data_is_one_clear_error(info, tmp_path, text, sidecar, fragment):
    with pytest.raises(FmuBuilderError, match=fragment):
        load_data(write(tmp_path, text, sidecar), info)


def test_the_sensor_model_matches_the_analytic_step_response():
    """A unit step at t = 0 (two records at the same time: before and after it)."""
    time = np.linspace(0.0, 1.0, 1001)
    lagged = first_order_lag(np.concatenate([[0.0], time]), np.concatenate([[0.0], np.ones_like(time)]), 0.1)[1:]
    np.testing.assert_allclose(lagged, 1.0 - np.exp(-time / 0.1), atol=1e-12)


@pytest.mark.parametrize("sidecar, fragment", [
    ({"start_values": [1, 2]}, "start_values is [1, 2], not a JSON object"),
    ({"start_values": {"J": "0_02"}}, "without '_'"),
    ({"start_values": {"inertia": True}}, "not a value of the Real variable inertia"),
    ({"start_values": {"inertia": "heavy"}}, "not a value of the Real variable inertia"),
    ({"start_values": {"J": {"value": 1}}}, "start_values.J"),
    ('{"start_values": {"J": NaN}}', "start_values.J"),
    ({"sensor_lag": "fast"}, "sensor_lag"),
    ({"bench": 3}, "bench is 3"),
    ({"bench": {"runs": "two"}}, "bench.runs"),
    ({"bench": {"runs": 1.5}}, "bench.runs"),
    ({"bench": {"fine_step": 0}}, "bench.fine_step"),
    ({"truth": {"parameters": 7}}, "truth.parameters"),
])
def test_every_wrong_type_in_a_sidecar_is_one_line(info, tmp_path, sidecar, fragment):
    with pytest.raises(FmuBuilderError, match=re.escape(fragment)):
        load_data(write(tmp_path, ROWS, sidecar), info)


def test_a_number_written_with_an_underscore_is_refused(info, tmp_path):
    path = write(tmp_path, ROWS.replace("\n0.5,5,", "\n0.5,1_000,", 1))
    with pytest.raises(FmuBuilderError, match="row 7, column 'speed': '1_000'"):
        load_data(path, info)
