"""The training reads a measured output that the hybrid sets equal to a corrected derivative (the
DC drive's power, der(energy)) from the hybrid's derivative, as the exported hybrid shows it
(TrainSettings.aliases). Read from the FMU it stays the plain model's whatever the ANN does to
der(energy), and the loss on it can only be lowered through the other channels.

The reference is the DC drive's speed-current-loss truth (examples/dc_drive/model.c): its loss
0.01 |speed * current| enters der(energy) and the power alone, so the declared model runs the same
states and the truth's power is the declared model's plus the loss."""
import numpy as np
import pytest
import torch

from fmubuilder.build import example_fmu
from fmubuilder.data import MeasuredData
from fmubuilder.neural.model import NeuralFMU
from fmubuilder.neural.topology import TopologyConfig
from fmubuilder.neural.train import TrainSettings, Trainer, evaluate
from fmubuilder.simulation import simulate

STOP, STEP = 10.0, 0.01


@pytest.fixture(scope="module")
def runs():
    """(data: the truth's power and energy, noise-free, every 0.05 s; the loss along the run there)."""
    kw = dict(stop_time=STOP, solver="rk4", step_size=STEP, output_interval=0.05, variables=["power", "energy"])
    truth, plain = simulate(example_fmu("dc_drive_truth_speed_current_loss"), **kw), \
        simulate(example_fmu("dc_drive"), **kw)
    data = MeasuredData(truth.time, {"power": np.asarray(truth["power"], dtype=float),
                                     "energy": np.asarray(truth["energy"], dtype=float)}, source="dc_drive loss")
    return data, np.asarray(truth["power"], dtype=float) - np.asarray(plain["power"], dtype=float)


@pytest.mark.parametrize("aliases", [{"power": "der(energy)"}, {}])
def test_the_power_loss_sees_the_correction_of_der_energy(dc_drive_fmu, runs, aliases):
    data, loss = runs
    settings = TrainSettings(epochs=1, element_length=2.5, step_size=STEP, solver="rk4", progress=False,
                             sensor_lag=0.0, loss_signals=["power"], aliases=aliases)
    torch.manual_seed(0)
    config = TopologyConfig(channels=["der(energy)"], inputs=["speed"], hidden=[4], kind="residual")
    with NeuralFMU(dc_drive_fmu, config) as model:
        trainer = Trainer(model, data, settings, 0.0)
        trainer.prepare()
        assert trainer.signal_losses()["power"] == pytest.approx(1.0)      # the plain FMU's error: the scale
        with torch.no_grad():                   # the correction: a constant, the loss's mean
            model.topology.post_shift.fill_(float(np.mean(loss)))
        trainer._capture_starts(plain=False)
        ratio = trainer.signal_losses()["power"]
        mse = evaluate(model, data, STEP, "rk4", aliases=aliases)["power"]["mse"]
    if aliases:
        expected = np.mean((loss - np.mean(loss)) ** 2)
        # (the elements share their boundary samples: the loss weighs those twice)
        assert ratio == pytest.approx(expected / np.mean(loss ** 2), rel=3e-2)
        assert ratio < 0.8
        assert mse == pytest.approx(expected, rel=1e-3)
    else:       # without the alias the power is the FMU's: the correction cannot touch it
        assert ratio == pytest.approx(1.0, rel=1e-9)
        assert mse == pytest.approx(np.mean(loss ** 2), rel=1e-3)
