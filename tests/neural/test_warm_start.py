"""The warm start: the ANN fitted to the closed-loop collocation estimate of the missing term,
checked against the term compiled into the DC drive's truth variant (windage)."""
import numpy as np
import pytest
import torch

from fmubuilder.build import example_fmu
from fmubuilder.data import MeasuredData
from fmubuilder.neural.train import train_neural_fmu
from fmubuilder.simulation import simulate

# examples/dc_drive/model.c: windage torque 3e-6 * w|w| on an inertia of 0.01 kg m2.
WINDAGE_PER_INERTIA = 3e-6 / 0.01


@pytest.fixture(scope="module")
def windage_data():
    """10 s of the speed-controlled drive with undeclared windage; speed and current measured with noise."""
    truth = simulate(example_fmu("dc_drive_truth_windage"), stop_time=10.0, solver="rk4", step_size=0.0005,
                     output_interval=0.01, variables=["speed", "current"])
    rng = np.random.default_rng(0)
    signals = {"speed": truth["speed"] + 0.5 * rng.standard_normal(truth.time.size),
               "current": truth["current"] + 0.05 * rng.standard_normal(truth.time.size)}
    return MeasuredData(truth.time, signals, source="dc_drive windage")


def first_loss(fmu, data, warm_start: bool):
    """The training loss of the start parameters (one element batch: the first epoch measures them)
    and the trained model."""
    result = train_neural_fmu(fmu, data, targets=["der(speed)"], inputs=["speed"], topology="residual", hidden=[8],
                              epochs=1, element_length=2.0, step_size=0.002, progress=False,
                              warm_start=warm_start, ccpt_window=0.2)
    return result.history[0]["loss"], result


def test_warm_start_lowers_the_initial_loss_and_finds_the_windage(dc_drive_fmu, windage_data):
    zero_init, plain = first_loss(dc_drive_fmu, windage_data, warm_start=False)
    plain.model.close()
    warm, result = first_loss(dc_drive_fmu, windage_data, warm_start=True)
    try:
        assert zero_init == pytest.approx(1.0)         # the residual ANN starts at zero: the plain FMU
        assert warm < 0.7 * zero_init
        assert result.metrics["warm_start"]["samples"] > 1000
        speeds = torch.tensor([[100.0], [150.0]], dtype=torch.float64)
        with torch.no_grad():
            learned = result.model.topology.correction(speeds)[:, 0].numpy()
        expected = -WINDAGE_PER_INERTIA * speeds[:, 0].numpy() ** 2
        np.testing.assert_allclose(learned, expected, rtol=0.25)
    finally:
        result.model.close()
