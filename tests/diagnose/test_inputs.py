"""The diagnosis drives the FMU's inputs from the data's input columns, as every other stage does.

The data are simulated by fmpy (CVode, an independent simulator) from the sampled speed drive
(examples/sampled_plant), whose set point is an FMU input, with white noise added. On the model's
own data the diagnosis must find nothing; with twice the viscous friction in the truth it must find it.
Without the inputs the declared model would hold its default set point, and its own data would look
like a large effect.
"""
import csv

import numpy as np
import pytest
from fmpy import simulate_fmu

from fmubuilder.build import example_fmu
from fmubuilder.diagnose import diagnose

STOP = 12.0
NOISE = {"w": 0.02, "i": 0.05}


def _setpoint_profile():
    t = np.linspace(0.0, STOP, 49)
    values = 4.0 * np.sin(0.9 * t) + 2.0 * np.sign(np.sin(0.31 * t + 0.5))
    return np.array(list(zip(t, values)), dtype=[("time", float), ("setpoint", float)])


def _measure(folder, name, start_values=None, seed=0):
    profile = _setpoint_profile()
    result = simulate_fmu(str(example_fmu("sampled_plant")), fmi_type="ModelExchange", solver="CVode",
                          stop_time=STOP, output_interval=0.05, input=profile, start_values=start_values or {},
                          output=list(NOISE), relative_tolerance=1e-8, record_events=False)
    rng = np.random.default_rng(seed)
    path = folder / f"{name}.csv"
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["time", *NOISE, "setpoint"])
        setpoint = np.interp(result["time"], profile["time"], profile["setpoint"])
        noisy = {n: result[n] + rng.normal(0.0, s, result.size) for n, s in NOISE.items()}
        for k, t in enumerate(result["time"]):
            writer.writerow([repr(float(t)), *(repr(float(noisy[n][k])) for n in NOISE), repr(float(setpoint[k]))])
    return path


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return tmp_path_factory.mktemp("diagnose_inputs")


def test_the_models_own_data_driven_by_an_input_show_no_effect(folder):
    d = diagnose(example_fmu("sampled_plant"), _measure(folder, "own"))
    assert not d.significant, [(e.signal, e.rms, e.noise) for e in d.errors]
    for e in d.errors:
        assert e.rms < 1.3 * NOISE[e.signal], e


def test_a_parameter_error_under_an_input_is_found(folder):
    d = diagnose(example_fmu("sampled_plant"), _measure(folder, "more_friction", start_values={"b": 0.1}))
    assert d.significant
