"""SimulationResult: access by name and CSV output read back by the signal reader."""
import io

import numpy as np
import pytest

from fmubuilder.errors import FmuBuilderError
from fmubuilder.simulation import SimulationResult, read_csv_signals


def sample_result():
    return SimulationResult(
        time=np.array([0.0, 0.1, 0.2]),
        values={"h": np.array([1.0, 0.1 + 0.2, -1e-300]), "bounces": np.array([0, 1, 2], dtype=np.int64),
                "flag": np.array([False, True, True])})


def test_access_by_name():
    result = sample_result()
    assert result.names == ["h", "bounces", "flag"]
    np.testing.assert_array_equal(result["time"], [0.0, 0.1, 0.2])
    assert result["bounces"].dtype == np.int64
    with pytest.raises(FmuBuilderError, match="'v' was not recorded; recorded: h, bounces, flag"):
        result["v"]


def test_csv_round_trip_is_exact(tmp_path):
    result = sample_result()
    path = tmp_path / "out.csv"
    result.to_csv(path)
    assert path.read_text().splitlines()[0] == "time,h,bounces,flag"
    time, columns = read_csv_signals(path)
    np.testing.assert_array_equal(time, result.time)
    np.testing.assert_array_equal(columns["h"], result["h"])        # shortest repr reads back exactly
    np.testing.assert_array_equal(columns["bounces"], [0, 1, 2])
    np.testing.assert_array_equal(columns["flag"], [0, 1, 1])


def test_csv_replaces_an_existing_file_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "out.csv"
    path.write_text("old")
    sample_result().to_csv(path)
    assert path.read_text().startswith("time,")
    assert [p.name for p in tmp_path.iterdir()] == ["out.csv"]


def test_csv_to_a_stream_and_into_a_missing_folder(tmp_path):
    stream = io.StringIO()
    sample_result().to_csv(stream)
    assert stream.getvalue().count("\n") == 4
    with pytest.raises(FmuBuilderError, match="does not exist; create it first"):
        sample_result().to_csv(tmp_path / "missing" / "out.csv")
