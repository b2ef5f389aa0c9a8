"""Fixtures of the NeuralFMU tests: example FMUs (built on demand, cached) and small data sets
generated with fmubuilder's engine from the same C models with a modified parameter."""
import numpy as np
import pytest
import torch

from fmubuilder.build import example_fmu


@pytest.fixture(autouse=True)
def _single_thread():
    # Tiny tensors: one thread is fastest and keeps timings steady on a shared machine.
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture(scope="session")
def ball_fmu():
    return example_fmu("bouncing_ball")


@pytest.fixture(scope="session")
def plant_fmu():
    return example_fmu("sampled_plant")


@pytest.fixture(scope="session")
def vldm_fmu():
    return example_fmu("vldm")


@pytest.fixture(scope="session")
def dc_drive_fmu():
    return example_fmu("dc_drive")


def plant_data(path, times, setpoints, stop, seed, friction=0.2, noise=0.002):
    """sampled_plant driven by a set-point profile, with a different viscous friction `b` than the
    declared 0.05 (the effect the ANN has to learn), speed w measured with noise."""
    from fmubuilder.data import MeasuredData
    from fmubuilder.simulation import simulate
    result = simulate(path, start_time=0.0, stop_time=stop, start_values={"b": friction},
                      inputs={"time": np.asarray(times, float), "setpoint": np.asarray(setpoints, float)},
                      solver="rk4", step_size=0.001, output_interval=0.01, variables=["w", "i", "u"])
    rng = np.random.default_rng(seed)
    w = result["w"] + noise * rng.standard_normal(result.time.size)
    setpoint = np.interp(result.time, times, setpoints)
    return MeasuredData(result.time, {"w": w}, {}, {"setpoint": setpoint}, "synthetic"), result
