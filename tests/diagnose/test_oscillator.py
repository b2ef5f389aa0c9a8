"""An effect that is not slow: an oscillator whose damping is off shows at its own frequency.

The data come from the Van der Pol Reference FMU (not ours) simulated by fmpy (CVode) with mu 20 %
above the declared value, sampled at 20 Hz, with AR(1) noise (correlation 0.6 between samples).
The residual then lies at the oscillation's frequency and its harmonics, far above the lowest
Fourier frequencies; the diagnosis must call it significant, and must not on the declared model's
own data with the same coloured noise.
"""
import csv

import numpy as np
import pytest
from fmpy import simulate_fmu

from fmubuilder.diagnose import diagnose

from ..reference_fmus import reference_fmu

STOP, INTERVAL = 20.0, 0.05
SIGMA, RHO = 0.02, 0.6


def _ar1(n, rng):
    e = np.empty(n)
    e[0] = rng.normal()
    for k in range(1, n):
        e[k] = RHO * e[k - 1] + np.sqrt(1.0 - RHO ** 2) * rng.normal()
    return SIGMA * e


def _measure(fmu, path, mu, seed):
    result = simulate_fmu(str(fmu), fmi_type="ModelExchange", solver="CVode", stop_time=STOP,
                          output_interval=INTERVAL, start_values={"mu": mu}, output=["x0", "x1"],
                          relative_tolerance=1e-9, record_events=False)
    rng = np.random.default_rng(seed)
    noisy = {name: result[name] + _ar1(result.size, rng) for name in ("x0", "x1")}
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["time", "x0", "x1"])
        for k, t in enumerate(result["time"]):
            writer.writerow([repr(float(t)), repr(float(noisy["x0"][k])), repr(float(noisy["x1"][k]))])
    return path


@pytest.mark.parametrize("seed", [0, 1])
def test_a_damping_error_of_an_oscillator_is_significant(tmp_path, seed):
    fmu = reference_fmu("VanDerPol")
    d = diagnose(fmu, _measure(fmu, tmp_path / "mu.csv", 1.2, seed))
    assert d.significant, (d.p_value, [(e.signal, e.rms, e.noise) for e in d.errors])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_oscillators_own_data_with_coloured_noise_are_not_significant(tmp_path, seed):
    fmu = reference_fmu("VanDerPol")
    d = diagnose(fmu, _measure(fmu, tmp_path / "own.csv", 1.0, seed))
    assert not d.significant, (d.p_value, [(e.signal, e.rms, e.noise) for e in d.errors])
