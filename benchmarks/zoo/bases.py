"""The base models of the effect zoo: a declared FMU, what is measured on it, which derivatives an
effect may enter, which parameters may be wrong, and how a run is excited.

Each base draws a run's excitation from a random generator: start values (oscillators, decays, a
drive's warm or cold start) and, for an FMU with inputs, an input signal; training, validation and
test runs draw theirs independently, so they differ.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

HERE = Path(__file__).resolve().parent
REFERENCE_FMUS = HERE / "reference_fmus"


@dataclass
class Run:
    """One run's excitation: start values and FMU inputs as (time, values) samples (none: {})."""
    duration: float
    start_values: dict = field(default_factory=dict)
    inputs: dict[str, Callable[[np.ndarray], np.ndarray]] = field(default_factory=dict)


@dataclass
class Base:
    name: str
    fmu: Callable[[], Path]
    signals: list[str]              # measured
    channels: list[str]             # derivatives an effect may enter (the physics, not a controller)
    parameters: list[str]           # parameters a truth may have wrong
    draw_run: Callable[[np.random.Generator], Run]


def _example(name: str) -> Callable[[], Path]:
    def path() -> Path:
        from fmubuilder.build import example_fmu
        return example_fmu(name)
    return path


def _reference(name: str) -> Callable[[], Path]:
    return lambda: REFERENCE_FMUS / f"{name}.fmu"


def _steps(rng: np.random.Generator, duration: float, low: float, high: float, mean_hold: float):
    """A random staircase with ramps: holds of random length, each level uniform in [low, high],
    joined by ramps of 0-30 % of the hold; returned as a function of time (piecewise linear)."""
    times, levels, t = [0.0], [rng.uniform(low, high)], 0.0
    while t < duration:
        hold = rng.exponential(mean_hold) + 0.2 * mean_hold
        ramp = rng.uniform(0.0, 0.3) * hold
        t += hold
        times += [t, t + ramp]
        levels += [levels[-1], rng.uniform(low, high)]
        t += ramp
    times, levels = np.array(times), np.array(levels)
    return lambda at: np.interp(at, times, levels)


def _dc_drive_run(rng):
    # The profile is inside the FMU: runs differ in their length (15-20 s: start-up, load steps, a
    # slower speed, the reversal's start) and their start (a warm or cold winding, a turning rotor).
    return Run(float(rng.uniform(15.0, 20.0)), {"temperature": float(rng.uniform(283.0, 330.0)), "speed": float(rng.uniform(-50.0, 50.0))})


def _sampled_plant_run(rng):
    duration = float(rng.uniform(6.0, 10.0))
    return Run(duration, {}, {"setpoint": _steps(rng, duration, -3.0, 3.0, mean_hold=1.5)})


def _van_der_pol_run(rng):
    radius, angle = rng.uniform(0.5, 3.0), rng.uniform(0.0, 2 * np.pi)
    return Run(float(rng.uniform(8.0, 15.0)), {"x0": float(radius * np.cos(angle)), "x1": float(radius * np.sin(angle))})


def _dahlquist_run(rng):
    return Run(float(rng.uniform(3.0, 6.0)), {"x": float(rng.choice([-1, 1]) * rng.uniform(1.0, 4.0))})


BASES = [
    Base("dc_drive", _example("dc_drive"), ["current", "speed", "temperature", "energy"],
         ["der(current)", "der(speed)", "der(temperature)", "der(energy)"],
         ["inertia", "viscous_friction", "nominal_resistance", "thermal_resistance", "motor_constant"],
         _dc_drive_run),
    Base("sampled_plant", _example("sampled_plant"), ["i", "w"], ["der(i)", "der(w)"],
         ["R", "J", "b", "K"], _sampled_plant_run),
    Base("VanDerPol", _reference("VanDerPol"), ["x0", "x1"], ["der(x0)", "der(x1)"], ["mu"], _van_der_pol_run),
    Base("Dahlquist", _reference("Dahlquist"), ["x"], ["der(x)"], ["k"], _dahlquist_run),
]
