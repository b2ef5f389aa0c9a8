"""The collocation estimate of a missing term in a derivative that reads an unmeasured state (the DC
drive's der(energy) = voltage * current, the voltage from the speed controller's integrator),
checked against the loss compiled into the DC drive's speed-current-loss truth
(examples/dc_drive/model.c: 0.01 W.s/(rad.A) * |speed * current|) along the truth's own run."""
import numpy as np
import pytest

from fmubuilder import synth
from fmubuilder.build import example_fmu
from fmubuilder.data import load_data
from fmubuilder.examples_zoo import SENSOR_NOISE
from fmubuilder.neural.collocation import forced_channel_run, samples_along
from fmubuilder.neural.model import NeuralFMU
from fmubuilder.neural.topology import TopologyConfig
from fmubuilder.simulation import simulate

LOSS_COEFFICIENT = 0.01     # examples/dc_drive/model.c, SPEED_CURRENT_LOSS


@pytest.fixture(scope="module")
def loss_data(tmp_path_factory):
    """The DC drive's 30 s profile logged from the loss truth at 10 Hz with the bench's sensor lag and
    its coloured noise (the bundled data's levels)."""
    settings = synth.BenchSettings(signals=("speed", "current", "power", "energy", "temperature"),
                                   noise_std={"speed": 0.1, "current": 0.02, "power": 1.0, "energy": 1.0,
                                              "temperature": 0.02},
                                   seed=3, **SENSOR_NOISE)
    truth = example_fmu("dc_drive_truth_speed_current_loss")
    path = tmp_path_factory.mktemp("loss") / "loss.csv"
    synth.write_measurement(synth.measure(truth, stop_time=30.0, settings=settings), path)
    return truth, path


# with the power measured the estimate is its difference (its noise about 1 W rms); without it, the
# energy's slope (about 2.5 W rms over 0.5 s lines, more at the run's ends)
@pytest.mark.parametrize("power, rms_share", [(True, 0.4), (False, 0.7)])
def test_the_energy_estimate_follows_the_loss_not_the_integrators_drift(dc_drive_fmu, loss_data, power, rms_share):
    truth_fmu, path = loss_data
    model = NeuralFMU(dc_drive_fmu, TopologyConfig(channels=["der(energy)"], inputs=["speed"], hidden=[4],
                                                   kind="residual"))
    try:
        data = load_data(path, model.info)
        if not power:
            del data.signals["power"]
        lag = data.sensor_lag or 0.0
        run = forced_channel_run(model, data, 0.01, "rk4", 0.5, data.input_signals(model.info), lag)
        times, inputs, fmu_channels, measured, mask = samples_along(run, model, data, 0.5, lag)
    finally:
        model.close()
    truth = simulate(truth_fmu, start_time=data.start, stop_time=data.stop, variables=["speed", "current"],
                     solver="rk4", step_size=0.001, output_interval=0.001)
    speed, current = (np.interp(times, truth.time, np.asarray(truth[n], dtype=float)) for n in ("speed", "current"))
    loss = LOSS_COEFFICIENT * np.abs(speed * current)
    kept = mask[:, 0]
    assert kept.mean() > 0.3
    error = (measured[:, 0] - fmu_channels[:, 0] - loss)[kept]
    size = np.sqrt(np.mean(loss[kept] ** 2))
    # with the integrator left to integrate the measured speed, the error was 16 W on average
    assert abs(np.mean(error)) < 0.1 * size
    assert np.sqrt(np.mean(error ** 2)) < rms_share * size
