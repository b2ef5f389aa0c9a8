"""No training through the solver where the hybrid already sits at the noise floor on every training
signal (TrainSettings.floor_factor): data made by the declared plant itself plus noise of a known
variance, against data with an undeclared friction."""
import numpy as np
import pytest

from fmubuilder.data import MeasuredData
from fmubuilder.neural.train import train_neural_fmu
from fmubuilder.simulation import simulate

NOISE = 0.002          # standard deviation of the measured speed's noise
RUNS = 2               # the data's mean over two runs: the spread column is NOISE * sqrt(RUNS)
COMMON = dict(targets=["der(w)"], inputs=["w"], topology="residual", hidden=[8], element_length=4.0,
              step_size=0.002, solver="rk4", loss_scale="noise", budget=3, optimizer="adam", progress=False)


def measured(plant_fmu, friction: float, seed: int = 0):
    """(data, the noise added): the plant with viscous friction `friction` (declared: 0.05) driven by a
    set-point step, its speed with white noise; the spread column says the noise's size."""
    times, setpoints = [0.0, 1.0, 1.001, 4.0], [1.0, 1.0, 2.0, 2.0]
    run = simulate(plant_fmu, start_time=0.0, stop_time=4.0, start_values={"b": friction},
                   inputs={"time": np.asarray(times), "setpoint": np.asarray(setpoints)},
                   solver="rk4", step_size=0.001, output_interval=0.01, variables=["w"])
    noise = NOISE * np.random.default_rng(seed).standard_normal(run.time.size)
    data = MeasuredData(run.time, {"w": run["w"] + noise}, std={"w": np.full(run.time.size, NOISE * np.sqrt(RUNS))},
                        inputs={"setpoint": np.interp(run.time, times, setpoints)}, runs=RUNS, source="plant")
    return data, noise


def test_a_model_at_the_noise_floor_is_not_trained(plant_fmu):
    """The residual ANN starts at zero, the declared plant, which made the data: its MSE over the
    noise variance is what the noise alone gives, within the factor, so no loss is evaluated."""
    data, noise = measured(plant_fmu, friction=0.05)
    result = train_neural_fmu(plant_fmu, data, floor_factor=1.5, **COMMON)
    result.model.close()
    floor = result.metrics["at_noise_floor"]
    assert result.metrics["loss_evaluations"] == 0 and floor["factor"] == 1.5
    # the ratio is the noise's own mean square over its variance (the engine's run of the declared
    # plant is the generator's, to far below the noise)
    assert floor["ratios"]["w"] == pytest.approx(np.mean(noise ** 2) / NOISE ** 2, rel=1e-4)


def test_the_factor_decides_and_an_effect_is_trained(plant_fmu):
    """Just below the noise's own ratio the same model trains its whole budget, just above it not at
    all; with the undeclared friction (far above the floor) it trains at the first test's factor."""
    data, noise = measured(plant_fmu, friction=0.05)
    ratio = np.mean(noise ** 2) / NOISE ** 2
    for factor, evaluations in ((0.99 * ratio, 3), (1.01 * ratio, 0)):
        result = train_neural_fmu(plant_fmu, data, floor_factor=factor, **COMMON)
        result.model.close()
        assert result.metrics["loss_evaluations"] == evaluations, factor
    effect, _ = measured(plant_fmu, friction=0.2)
    result = train_neural_fmu(plant_fmu, effect, floor_factor=1.5, **COMMON)
    result.model.close()
    assert result.metrics["loss_evaluations"] == 3 and result.metrics["at_noise_floor"] is None


def test_without_the_noise_s_size_the_model_is_trained(plant_fmu):
    """No spread column: the data do not say where the floor is, and the training runs."""
    data, _ = measured(plant_fmu, friction=0.05)
    data.std = {}
    result = train_neural_fmu(plant_fmu, data, floor_factor=1e9, **COMMON)
    result.model.close()
    assert result.metrics["loss_evaluations"] == 3 and result.metrics["at_noise_floor"] is None
