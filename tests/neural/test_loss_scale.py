"""The divisor of each signal's MSE in the training loss (TrainSettings.loss_scale): the plain FMU's
MSE, or the signal's noise variance from the data's spread columns."""
import math

import numpy as np
import pytest
import torch

from fmubuilder.data import MeasuredData
from fmubuilder.errors import FmuBuilderError
from fmubuilder.neural.model import NeuralFMU
from fmubuilder.neural.topology import TopologyConfig
from fmubuilder.neural.train import Trainer, TrainSettings, noise_scale, train_neural_fmu

from .conftest import plant_data

NOISE = 0.002


def test_noise_scale_is_the_noise_variance_where_the_data_have_a_spread():
    time = np.arange(0.0, 1.0, 0.1)
    data = MeasuredData(time, {"a": np.zeros_like(time), "b": np.zeros_like(time)},
                        {"a": np.full_like(time, 0.3)}, runs=3)
    scale = noise_scale(data, {"a": 7.0, "b": 5.0})
    assert scale["a"] == pytest.approx(0.3 ** 2 / 3)     # the spread's mean square over the runs
    assert scale["b"] == 5.0                             # no spread column: the plain FMU's MSE


@pytest.fixture(scope="module")
def plant_with_spread(plant_fmu):
    data, _ = plant_data(plant_fmu, [0, 1, 1.001, 2.5, 2.501, 4], [1, 1, 2, 2, 0.5, 0.5], 4.0, seed=0,
                         noise=NOISE)
    data.std = {"w": np.full_like(data.time, NOISE)}
    data.runs = 1
    return data


def _loss_at_start(plant_fmu, data, loss_scale: str) -> tuple[float, dict]:
    """The training loss of the untrained hybrid (the residual ANN's last layer is zero: the plain
    FMU) over one element, and the loss's divisors."""
    settings = TrainSettings(element_length=10.0, step_size=0.002, solver="rk4", progress=False, sensor_lag=0.0,
                             loss_scale=loss_scale)
    config = TopologyConfig(channels=["der(w)"], inputs=["w"], hidden=[8], kind="residual")
    torch.manual_seed(0)
    with NeuralFMU(plant_fmu, config) as model:
        trainer = Trainer(model, data, settings, 0.0)
        trainer.prepare()
        with torch.no_grad():
            return float(trainer.batch_loss(trainer.elements, carry=False)), dict(trainer.scale)


def test_the_noise_scaled_loss_counts_the_plain_error_in_noise_variances(plant_fmu, plant_with_spread):
    plain_loss, plain_scale = _loss_at_start(plant_fmu, plant_with_spread, "plain")
    noise_loss, noise_scale_ = _loss_at_start(plant_fmu, plant_with_spread, "noise")
    assert plain_loss == pytest.approx(1.0)                  # the plain FMU over its own MSE
    assert noise_scale_["w"] == pytest.approx(NOISE ** 2)
    # the same simulation and MSE, divided by the noise variance instead: the friction's error
    # (0.2 against the declared 0.05) is far above the noise
    assert noise_loss == pytest.approx(plain_scale["w"] / NOISE ** 2, rel=1e-9)
    assert noise_loss > 10.0 and math.isfinite(noise_loss)


def test_an_unknown_loss_scale_is_refused(plant_fmu, plant_with_spread):
    with pytest.raises(FmuBuilderError, match="unknown loss scale 'noisy'"):
        train_neural_fmu(plant_fmu, plant_with_spread, targets=["der(w)"], inputs=["w"], loss_scale="noisy",
                         progress=False)
