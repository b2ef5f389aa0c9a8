"""Saving/loading a trained NeuralFMU and the `fmubuilder train` command."""
import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch

from fmubuilder.errors import FmuBuilderError
from fmubuilder.neural import NeuralFMU, TopologyConfig, simulate
from fmubuilder.cli import run as train_main
from fmubuilder.neural.io import load_neural_fmu, read_neural_fmu, save_neural_fmu

from .conftest import plant_data


def test_save_load_roundtrip(plant_fmu, ball_fmu, tmp_path):
    torch.manual_seed(0)
    model = NeuralFMU(plant_fmu, TopologyConfig(channels=["der(w)"], inputs=["w", "der(w)"], hidden=[5]),
                      start_values={"b": "0.1"})
    with torch.no_grad():
        for p in model.topology.parameters():
            p.add_(0.1 * torch.randn_like(p))
    path = save_neural_fmu(model, tmp_path / "model.nfmu", metadata={"note": "test"})
    loaded = load_neural_fmu(path)
    assert loaded.config == model.config and loaded.start_values == {"b": 0.1}
    assert json.loads(json.dumps(read_neural_fmu(path)["config"])) == model.config.to_dict()
    with torch.no_grad():
        a = simulate(model, 0.2, 0.002, record=["w", "der(w)"])
        b = simulate(loaded, 0.2, 0.002, record=["w", "der(w)"])
    assert torch.equal(a.values, b.values)
    # the FMU moved: give its new place; another FMU is refused by its GUID
    moved = tmp_path / "moved.fmu"
    shutil.copy(plant_fmu, moved)
    load_neural_fmu(path, fmu=moved).close()
    with pytest.raises(FmuBuilderError, match="GUID"):
        load_neural_fmu(path, fmu=ball_fmu)
    (tmp_path / "junk.nfmu").write_bytes(b"not a model")
    with pytest.raises(FmuBuilderError, match="not a trained NeuralFMU"):
        load_neural_fmu(tmp_path / "junk.nfmu")
    for m in (model, loaded):
        m.close()


def write_csv(path, data, extra=()):
    columns = {"time": data.time, **data.signals, **data.inputs, **dict(extra)}
    rows = np.column_stack(list(columns.values()))
    np.savetxt(path, rows, delimiter=",", header=",".join(columns), comments="", fmt="%.10g")


def test_train_command(plant_fmu, tmp_path):
    data, _ = plant_data(plant_fmu, [0, 1, 1.001, 2], [1, 1, 2, 2], 2.0, seed=0)
    csv = tmp_path / "train.csv"
    write_csv(csv, data, extra={"w_std": np.full(data.time.size, 0.002)})
    out, metrics = tmp_path / "trained.nfmu", tmp_path / "metrics.json"
    args = [str(plant_fmu), "--data", str(csv), "--target", "der(w)", "--inputs", "w,der(w)", "--topology",
            "residual", "--hidden", "6", "--epochs", "2", "--element-length", "1", "--step-size", "0.002",
            "--ccpt", "300", "--quiet", "-o", str(out), "--json", str(metrics)]
    assert train_main(["train", *args]) == 0
    result = json.loads(metrics.read_text())
    assert set(result) >= {"errors", "seconds", "epochs"} and result["epochs"] == 2
    assert set(result["errors"]) == {"before", "after"} and set(result["errors"]["after"]["w"]) == {"mse", "max_abs", "final"}
    load_neural_fmu(out).close()
    assert train_main(["train", *args]) == 1  # exists without --force


def test_train_command_errors_are_one_line(plant_fmu, tmp_path):
    data, _ = plant_data(plant_fmu, [0, 1], [1, 1], 1.0, seed=0)
    csv = tmp_path / "train.csv"
    write_csv(csv, data, extra={"bogus": np.zeros(data.time.size)})
    command = [sys.executable, "-m", "fmubuilder.cli", "train", str(plant_fmu), "--data", str(csv),
               "--target", "der(w)", "--inputs", "w", "-o", str(tmp_path / "x.nfmu")]
    done = subprocess.run(command, capture_output=True, text=True)
    assert done.returncode == 1
    assert done.stderr.startswith("error: unknown variable 'bogus'") and done.stderr.count("\n") == 1


def test_negative_sensor_lag_is_a_one_line_error(plant_fmu, tmp_path, capsys):
    data, _ = plant_data(plant_fmu, [0, 1], [1, 1], 1.0, seed=0)
    csv = tmp_path / "train.csv"
    write_csv(csv, data)
    args = [str(plant_fmu), "--data", str(csv), "--target", "der(w)", "--inputs", "w", "--sensor-lag", "-0.1",
            "--quiet", "-o", str(tmp_path / "x.nfmu")]
    assert train_main(["train", *args]) == 1
    assert capsys.readouterr().err == "error: sensor lag must be >= 0 seconds, got -0.1\n"
    assert not (tmp_path / "x.nfmu").exists()
