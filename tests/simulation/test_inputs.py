"""Signal CSV files and input interpolation (numpy.interp as the reference)."""
import numpy as np
import pytest

from fmubuilder.errors import FmuBuilderError
from fmubuilder.fmi import read_model_info
from fmubuilder.simulation import simulate
from fmubuilder.simulation.inputs import InputSignals, input_signals_from, load_input_csv, read_csv_signals


def write(tmp_path, text, name="signals.csv"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_reads_columns_by_name(tmp_path):
    path = write(tmp_path, "time,a,b\n0,1,2.5\n0.5,-1e-3,3\n\n1.5, 4 ,5\n")
    time, columns = read_csv_signals(path)
    np.testing.assert_array_equal(time, [0.0, 0.5, 1.5])
    assert list(columns) == ["a", "b"]
    np.testing.assert_array_equal(columns["a"], [1.0, -1e-3, 4.0])


@pytest.mark.parametrize("text, message", [
    ("", "is empty"),
    ("t,a\n0,1\n", "the first column is 't', it must be 'time'"),
    ("time,a\n", "no data rows"),
    ("time,a,a\n0,1,2\n", "column 'a' appears twice"),
    ("time,a\n0,1\n1,x\n", r"row 3, column 'a': 'x' is not a number"),
    ("time,a\n0,1\n1,nan\n", r"row 3, column 'a': 'nan' is not a finite number"),
    ("time,a\n0,1\n1,\n", r"row 3, column 'a': '' is not a number"),
    ("time,a\n0,1\n1,2,3\n", r"row 3: 3 values for 2 columns"),
    ("time,a\n0,1\n1,2\n1,3\n", r"row 4: time 1.0 does not increase from the previous 1.0"),
    ("time,a\n0,1\n\n-1,2\n", r"row 4: time -1.0 does not increase"),
])
def test_malformed_files_fail_with_file_row_and_column(tmp_path, text, message):
    path = write(tmp_path, text)
    with pytest.raises(FmuBuilderError, match=message) as error:
        read_csv_signals(path)
    assert str(path) in str(error.value) and "\n" not in str(error.value)


def test_missing_file(tmp_path):
    with pytest.raises(FmuBuilderError, match="no such file"):
        read_csv_signals(tmp_path / "absent.csv")


def test_interpolation_matches_numpy_interp():
    rng = np.random.default_rng(7)
    time = np.cumsum(rng.uniform(0.01, 0.5, 40))
    values = rng.normal(size=(40, 2))
    info = _plant_info_stub()
    signals = InputSignals(time, {"u1": values[:, 0], "u2": values[:, 1]}, info)
    queries = np.concatenate([rng.uniform(time[0] - 1, time[-1] + 1, 300), time])
    for t in np.concatenate([np.sort(queries), queries]):       # monotone and random order
        expected = [np.interp(t, time, values[:, k]) for k in range(2)]
        np.testing.assert_allclose(signals.at(t), expected, rtol=1e-13, atol=1e-13)
    np.testing.assert_array_equal(signals.breakpoints, time)
    # several times at once (the NeuralFMU's batched solver): the values of at(t) one by one
    expected = np.stack([signals.at(t) for t in queries])
    np.testing.assert_allclose(signals.table(queries), expected, rtol=1e-13, atol=1e-13)
    assert signals.names == ["u1", "u2"]


def _plant_info_stub():
    from fmubuilder.fmi.model import Variable
    return [Variable(name, i, "Real", "input", "continuous") for i, name in enumerate(("u1", "u2"))]


def test_a_single_sample_is_a_constant_input():
    signals = InputSignals(np.array([1.0]), {"u1": np.array([3.0])}, _plant_info_stub()[:1])
    assert signals.at(0.0)[0] == signals.at(5.0)[0] == 3.0


def test_unknown_input_columns_list_the_model_inputs(tmp_path, example):
    info = read_model_info(example("sampled_plant"))
    path = write(tmp_path, "time,setpoint,torque\n0,1,0\n1,2,0\n")
    with pytest.raises(FmuBuilderError, match=r"'torque' is not an input of 'sampled_plant' \(its inputs: setpoint\)"):
        load_input_csv(path, info)
    with pytest.raises(FmuBuilderError, match="'w' is not an input"):
        input_signals_from({"time": [0.0, 1.0], "w": [1.0, 2.0]}, info)
    with pytest.raises(FmuBuilderError, match="no 'time' entry"):
        input_signals_from({"setpoint": [1.0]}, info)
    with pytest.raises(FmuBuilderError, match="sample 1: time 0.0 does not increase"):
        input_signals_from({"time": [0.0, 0.0], "setpoint": [1.0, 2.0]}, info)


def test_set_point_profile_from_csv_agrees_with_fmpy(tmp_path, example):
    """The sampled controller reads the set point at each 10 ms sample: a ramp and a step
    in the CSV must reach it as fmpy's input handling does."""
    import fmpy
    path = example("sampled_plant")
    profile = np.array([(0.0, 1.0), (0.3, 1.0), (0.5, 2.0), (0.8, 2.0), (0.805, 0.5), (1.2, 0.5)])
    csv = write(tmp_path, "time,setpoint\n" + "".join(f"{t!r},{v!r}\n" for t, v in profile.tolist()))
    ours = simulate(path, stop_time=1.2, input_csv=csv, rtol=1e-10, atol=1e-10, output_interval=0.001)
    signals = np.array([tuple(row) for row in profile], dtype=[("time", float), ("setpoint", float)])
    theirs = fmpy.simulate_fmu(str(path), stop_time=1.2, input=signals, relative_tolerance=1e-10,
                               output_interval=0.001, output=["w", "u"], record_events=False)
    np.testing.assert_allclose(theirs["time"], ours.time, atol=1e-12)
    for name in ("w", "u"):
        np.testing.assert_allclose(ours[name], theirs[name], rtol=0, atol=1e-7)
    assert ours.stats.time_events == 120


def test_discrete_inputs_hold_their_last_sample_and_report_changes():
    from fmubuilder.fmi.model import Variable
    variables = [Variable("gear", 0, "Integer", "input", "discrete"), Variable("on", 1, "Boolean", "input", "discrete")]
    time = np.array([0.0, 1.0, 2.0, 3.0])
    signals = InputSignals(time, {"gear": np.array([1, 1, 2, 2]), "on": np.array([0, 1, 1, 0])}, variables)
    assert signals.continuous == [] and signals.breakpoints.size == 0
    np.testing.assert_array_equal(signals.discrete_change_times(), [1.0, 2.0, 3.0])
    assert signals.discrete_at(-1.0) == {"gear": 1, "on": 0}
    assert signals.discrete_at(1.5) == {"gear": 1, "on": 1}
    assert signals.discrete_at(2.0) == {"gear": 2, "on": 1}      # a change at t applies from t on
