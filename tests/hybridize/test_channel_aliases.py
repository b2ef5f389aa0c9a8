"""Outputs that equal the corrected derivative (aliases) are found on the plain model's run
and written into the hybrid spec; fmpy's simulation of the plain FMU is the reference."""
import fmpy
import numpy as np

from fmubuilder.build import example_fmu
from fmubuilder.fmi import read_model_info
from fmubuilder.hybridize.workflow import channel_aliases

STOP = 5.0


def fmpy_aliases(fmu, info, channel):
    """Outputs whose fmpy trajectory equals the channel's to 1e-9 relative (and is not all 0)."""
    states = {s.name for s in info.states}
    outputs = [v.name for v in info.outputs if v.type == "Real" and v.name not in states]
    result = fmpy.simulate_fmu(str(fmu), stop_time=STOP, output=[*outputs, channel])
    d = result[channel]
    return {name: channel for name in outputs
            if np.any(result[name] != 0) and np.max(np.abs(result[name] - d)) <= 1e-9 * np.max(np.abs(result[name]))}


def test_power_is_found_as_alias_of_der_energy_and_nothing_else():
    fmu = example_fmu("dc_drive")
    info = read_model_info(fmu)
    times = np.linspace(0.0, STOP, 101)
    found = {channel: channel_aliases(fmu, info, channel, {}, times, 0.0, STOP)
             for channel in ("der(energy)", "der(speed)", "der(temperature)")}
    for channel, aliases in found.items():
        assert aliases == fmpy_aliases(fmu, info, channel), channel
    assert found["der(energy)"] == {"power": "der(energy)"}   # the C source: der(energy) = power
