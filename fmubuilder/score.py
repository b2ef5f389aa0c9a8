"""The score every choice on held-out data makes: the candidate chosen by `hybridize`
(hybridize/choice.py) and the parameters a training ends with (neural/train.py, Trainer's
validation). One score for both, so that a training stopped on it is never worse, in the measure
that chooses, than where it started (an ANN on a fitted term: than the term), up to how each side
simulates the model (the training its NeuralFMU, the choice the exported FMU). Both read their
engine runs alike: recorded on both sides of every event, the settled value at a sample
(docs/MEASUREMENTS.md, "One score for the choice and the training's stop").

The geometric mean replaced the arithmetic mean of MSE / MSE plain, which the signals the plain FMU
already fits decide: an energy 6 times worse moved it by 0.001, a speed 3 % better by 0.03.
"""
from __future__ import annotations

import math

import numpy as np


def validation_score(errors: dict, floors: dict) -> float:
    """Geometric mean over the signals of MSE / floor (inf when a candidate ran off); `errors` as
    train.data_errors gives them ({signal: {"mse": ...}})."""
    logs = []
    for signal, floor in floors.items():
        mse = errors[signal]["mse"]
        if not np.isfinite(mse):
            return float("inf")
        logs.append(math.log(max(mse, 1e-300) / floor))
    return math.exp(float(np.mean(logs))) if logs else 1.0


def floors_of(plain_errors: dict, noise: dict) -> dict:
    """Each signal's floor: its noise variance, else the plain FMU's MSE; signals with neither
    (a plain FMU exact on noise-free data) are left out."""
    floors = {}
    for signal, errors in plain_errors.items():
        floor = noise.get(signal)
        floor = floor if floor is not None and floor > 0 else errors["mse"]
        if floor > 0 and np.isfinite(floor):
            floors[signal] = floor
    return floors
