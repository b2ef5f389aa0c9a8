"""Measured data for the diagnosis tests: the example "truth" FMUs logged by the test bench
of fmubuilder.synth (sensor lag, jittered 10 Hz stamps, noise, two runs)."""
import pytest

from fmubuilder import synth
from fmubuilder.build import example_fmu
from fmubuilder.examples_zoo import SENSOR_NOISE

DC_DRIVE_BENCH = dict(signals=("speed", "current", "power", "temperature"),
                      noise_std={"speed": 0.1, "current": 0.02, "power": 1.0, "temperature": 0.02})
# synth's default noise levels, coloured like the bundled example data's
VLDM_BENCH = dict(signals=("speed", "power", "energy"), **SENSOR_NOISE)


def measure(folder, truth: str, *, stop_time: float, bench: dict, seed: int = 0, start_values=None):
    """CSV (and sidecar) of the example FMU `truth` logged by the bench; returns its path."""
    settings = synth.BenchSettings(seed=seed, **bench)
    measurement = synth.measure(example_fmu(truth), stop_time=stop_time, start_values=start_values, settings=settings)
    path = folder / f"{truth}_{seed}.csv"
    synth.write_measurement(measurement, path)
    return path


@pytest.fixture(scope="session")
def data_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("diagnose_data")
