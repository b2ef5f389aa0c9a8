"""The NeuralFMU training recipe of `hybridize`, stated once: `recipe_settings` gives the
TrainSettings it trains with, and `recipe_run` what it trains on from a run of data (its late share
held out, the solver's step). `fmubuilder train --recipe hybridize` reads the same, so that the
training `hybridize` ran can be run again, and varied, on its own (the report's "training" gives
the settings and the command).

The recipe settles how the network is trained. The run settles the rest: the derivatives and the
inputs (the diagnosis and the input choice), the signals in the loss, the budget and the seed.

Each constant is read when the settings are made: a benchmark may assign it (`recipe.OPTIMIZER = ...`).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..data import MeasuredData
from ..errors import FmuBuilderError
from ..neural.settings import TrainSettings

# Share of each training run (its end) held out of the fit, when no separate validation run is
# given: it picks the parameters the training ends with, and the candidate (workflow.Roles).
VALIDATION_SHARE = 0.2
# The optimizer through the solver. The loss is one smooth function of a few hundred parameters,
# each evaluation a simulation of all training data: a quasi-Newton step whose line search sizes
# it uses those evaluations better than fixed-size gradient steps (Adam), which must be told a
# step size and spend evaluations on steps that overshoot (benchmarks/bench_effects.py --optimizer).
OPTIMIZER = "lbfgs"
# The data cut into elements of at most MAX_ELEMENT_LENGTH seconds (at least MIN_ELEMENTS of
# them), all simulated side by side in one batch: one optimizer step per epoch, which lets the
# training rewind an epoch that made the loss worse (neural.train.Trainer._keep_best). A short run
# is one element: the loss must see a slow signal's drift (an integrator with a time constant of
# tens of seconds), which elements restarted from the measured states every few seconds hide. A
# long run restarts from the measured states every 100 s: several such time constants, while an
# element's run-off and its gradient's path through the solver stay bounded
# (benchmarks/bench_friction_training.py --elements).
MAX_ELEMENT_LENGTH = 100.0
MIN_ELEMENTS = 1
# Each signal's term of the loss is its MSE over its noise variance ("noise"), the unit of the
# validation score that chooses among the candidates (score.py). Over the plain FMU's MSE ("plain")
# a signal the plain model nearly fits weighs at its floor more than one hundreds of times off, and
# the steps trade the far-off signal for the other's noise (benchmarks/bench_friction_training.py
# --loss, bench_neural.py --loss-scale).
LOSS_SCALE = "noise"
# Before the training through the solver, the network is fitted to the collocation estimate of the
# missing term (neural/warm_start.py): no simulation with gradient, and the training starts near
# the effect. It is kept only if it lowers the training loss, so it never starts the training
# worse (benchmarks/bench_training.py).
WARM_START = True
# Seconds of data per local line of the warm start's collocation (neural/collocation.py), lines
# across input steps left out: long enough to average the noise of a few samples' slope, short
# against the effect's changes, so a line through a curved or stepped signal stays unbiased. On
# data at 10 Hz with a Coulomb friction, 0.5 s estimate it with an rms error of 7 % of its size,
# 1 s windows (all kept) 130 % (docs/CHANGELOG.md, "Integral (weak-form) target").
COLLOCATION_WINDOW = 0.5
# The warm start's target (neural/warm_start.py): "pointwise", the local lines' slopes, keeps the
# term's shape at the data's resolution; "integral", the state's increments over INTEGRAL_WINDOW
# seconds, averages more noise but needs the unmeasured integrators right: through `hybridize` it
# was better on one effect of four and ten times worse on another (bench_effects.py
# --warm-start-target integral).
WARM_START_TARGET = "pointwise"
INTEGRAL_WINDOW = 0.5
# After the training through the solver of a run trained as one element: Levenberg-Marquardt on the
# network's last layer, in which the correction is linear (neural/last_layer.py), this many
# simulations without gradient per loss evaluation of the budget. A simulation costs about 1/18 of
# a loss evaluation, so the refinement adds about as much work as the budget does
# (bench_effects.py --last-layer). Not on runs of several elements: refined over the whole of a long
# run, the validation scores fell while the test scores moved both ways, at tens of minutes of
# simulation (bench_neural.py --last-layer).
LAST_LAYER_SIMULATIONS_PER_EVALUATION = 20
# No training through the solver where the warm start leaves every training signal at its noise
# floor (choice.floor_factor: within the noise's spread of its variance): a step could lower the
# loss only by fitting the noise, and measured no such step scored better on the validation data
# (bench_effects.py). True: train anyway.
TRAIN_AT_FLOOR = False


def recipe_settings(time: np.ndarray, loss_signals: list[str] | None, budget: int, **run) -> TrainSettings:
    """The TrainSettings `hybridize` trains with on samples at `time`, the loss on `loss_signals`
    (None: all measured), for `budget` loss evaluations; `run`: the run's own fields (seed, solver,
    step_size, ...), and explicit changes of the recipe's."""
    span = float(time[-1] - time[0])
    element_length = min(MAX_ELEMENT_LENGTH, span / MIN_ELEMENTS)
    one_element = element_length >= span
    recipe = TrainSettings(
        budget=budget, element_length=element_length, loss_signals=loss_signals, loss_scale=LOSS_SCALE,
        warm_start=WARM_START, ccpt_window=COLLOCATION_WINDOW, warm_start_target=WARM_START_TARGET,
        integral_window=INTEGRAL_WINDOW, optimizer=OPTIMIZER,
        last_layer_simulations=LAST_LAYER_SIMULATIONS_PER_EVALUATION * budget if one_element else 0,
        floor_factor=_floor_factor(time))
    return replace(recipe, **run)


def _floor_factor(time: np.ndarray) -> float | None:
    from .choice import floor_factor
    return floor_factor([time]) if LOSS_SCALE == "noise" and not TRAIN_AT_FLOOR else None


@dataclass
class RecipeRun:
    """What `hybridize` trains on from one run of data: the samples of the fit, the held-out late
    share that picks the parameters the training ends with, the start values and the settings."""
    fit: MeasuredData
    validation: "Validation"      # neural.train.Validation
    start_values: dict
    settings: TrainSettings


def recipe_run(fmu: str | Path, data: str | Path | MeasuredData, start_values: dict | None,
               loss_signals: list[str] | None, budget: int, **run) -> RecipeRun:
    """The training `hybridize` runs on `data` given as its only training run: its last
    VALIDATION_SHARE held out, RK4 at the step every model is scored with (Scoring.checked on the
    fit's samples), the recipe's settings. A data file's sidecar gives start values under
    `start_values`; `run` as in recipe_settings (a solver or step given there is kept)."""
    from ..neural.train import Validation
    from .evaluate import Scoring, read_data
    if not isinstance(data, MeasuredData):
        from ..fmi import read_model_info
        data = read_data(Path(data), read_model_info(Path(fmu)))
        start_values = {**data.start_values, **(start_values or {})}
    start_values = dict(start_values or {})
    fit_window, validation_window = held_out_windows(data)
    fit = data.window(*fit_window)
    if "solver" not in run or "step_size" not in run:
        scoring = Scoring.checked(Path(fmu), fit, start_values)
        run = {"solver": scoring.solver, "step_size": scoring.step, **run}
    return RecipeRun(fit, Validation(data, validation_window, start_values), start_values,
                     recipe_settings(fit.time, loss_signals, budget, **run))


def held_out_windows(data: MeasuredData) -> tuple[tuple[float, float], tuple[float, float]]:
    """(the fit's window, the validation's) of a training run without a separate validation run:
    its last VALIDATION_SHARE held out of the fit."""
    split = _split_time(data)
    return (data.start, split), (_next_sample(data, split), data.stop)


def _split_time(data: MeasuredData) -> float:
    """The last sample before the held-out late share of a run."""
    split = data.start + (1.0 - VALIDATION_SHARE) * (data.stop - data.start)
    index = int(np.searchsorted(data.time, split, side="right")) - 1
    if index < 1 or index > data.time.size - 3:
        raise FmuBuilderError(f"{data.source} has too few samples to hold {VALIDATION_SHARE:.0%} of it out for "
                              "validation; give a separate run with --validation")
    return float(data.time[index])


def _next_sample(data: MeasuredData, t: float) -> float:
    return float(data.time[int(np.searchsorted(data.time, t, side="right"))])
