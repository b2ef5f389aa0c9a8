"""The ANN's inputs when a controller hides the missing term (fmubuilder.hybridize.inputs.inputs_through_loop).

A small closed loop simulated here, its truth known: a PI driver holds a car's speed on a target;
the truth has an extra drag 1.5 v + 0.06 v|v| that the model lacks. The driver compensates it, so
the speed's own missing term shows next to nothing; the drive energy shows the compensation. The
reference is the truth: the drag is a function of the speed alone, so the speed must be chosen,
and without the drag (the model is the truth) nothing.
"""
import numpy as np
import pytest

from fmubuilder.hybridize.inputs import MissingTerm, choose_inputs, inputs_through_loop
from fmubuilder.neural.collocation import local_slope

DT, EVERY = 0.01, 10                # simulation step; a sample every 0.1 s
DURATION = 120.0
MASS, KP, KI = 1000.0, 2000.0, 400.0


def _target(t, rng):
    frequencies, phases = rng.uniform(0.02, 0.1, 3), rng.uniform(0.0, 2 * np.pi, 3)
    return 12.0 + sum(3.0 * np.sin(2 * np.pi * f * t + p) for f, p in zip(frequencies, phases))


def _closed_loop(target, extra_drag: bool):
    """(speed, energy, drive force, acceleration) along the grid: explicit Euler of the loop."""
    n = target.size
    v, e, integral = np.empty(n), np.empty(n), 0.0
    force, acceleration = np.empty(n), np.empty(n)
    v[0], e[0] = target[0], 0.0
    for i in range(n):
        error = target[i] - v[i]
        force[i] = 200.0 + 0.4 * v[i] ** 2 + KP * error + KI * integral
        drag = 200.0 + 0.4 * v[i] * abs(v[i]) + ((1.5 * v[i] + 0.06 * v[i] * abs(v[i])) * 10 if extra_drag else 0.0)
        acceleration[i] = (force[i] - drag) / MASS
        if i + 1 < n:
            integral += DT * error
            v[i + 1] = v[i] + DT * acceleration[i]
            e[i + 1] = e[i] + DT * force[i] * v[i]
    return v, e, force, acceleration


def _term(seed: int, extra_drag: bool) -> MissingTerm:
    rng = np.random.default_rng(seed)
    grid = np.arange(0.0, DURATION, DT)
    target = _target(grid, rng)
    v, e, _, _ = _closed_loop(target, extra_drag)               # the "truth": measured with noise
    plain_v, plain_e, plain_force, plain_acceleration = _closed_loop(target, False)   # the model's plain run
    time = grid[::EVERY]
    measured_v = v[::EVERY] + 0.02 * rng.standard_normal(time.size)
    measured_e = e[::EVERY] + 100.0 * rng.standard_normal(time.size)
    slope_v, _ = local_slope(time, measured_v, time, 0.6)
    slope_e, _ = local_slope(time, measured_e, time, 0.6)
    missing = {"der(speed)": slope_v - plain_acceleration[::EVERY],
               "der(energy)": slope_e - (plain_force * plain_v)[::EVERY]}
    variables = {"speed": measured_v, "energy": measured_e, "drive_force": plain_force[::EVERY],
                 "noise": rng.standard_normal(time.size),
                 "der(speed)": plain_acceleration[::EVERY], "der(energy)": (plain_force * plain_v)[::EVERY]}
    kinds = {"speed": "state", "energy": "state", "drive_force": "local", "noise": "local",
             "der(speed)": "derivative", "der(energy)": "derivative"}
    return MissingTerm(time, missing, variables, kinds, {"speed", "energy"}, {})


def _masks(term):
    split = 0.8 * DURATION
    return term.time < split, term.time >= split


@pytest.mark.parametrize("seed", range(3))
def test_a_drag_the_driver_compensates_is_found_through_the_energy(seed):
    term = _term(seed, extra_drag=True)
    train, validation = _masks(term)
    own = choose_inputs(term, "der(speed)", train, validation)
    through = inputs_through_loop(term, "der(speed)", ["der(energy)"], train, validation)
    assert own.explained < 0.5          # the loop hides the drag in the speed's own estimate ...
    assert through is not None and through.inputs[0] == "speed"    # ... the energy shows it


@pytest.mark.parametrize("seed", range(3))
def test_without_a_missing_term_nothing_is_found_through_the_loop(seed):
    term = _term(seed, extra_drag=False)
    train, validation = _masks(term)
    assert inputs_through_loop(term, "der(speed)", ["der(energy)"], train, validation) is None
