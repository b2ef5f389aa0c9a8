"""The NeuralFMU training's settings and their defaults, in one place: `train_neural_fmu` takes
them, `fmubuilder train` reads its options' defaults from them, and hybridize/recipe.py states the
settings `hybridize` trains with. No torch here: the command line reads this before any training.
"""
from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class TrainSettings:
    epochs: int = 30
    budget: int | None = None         # loss evaluations instead of epochs: the training's work (see Trainer.fit)
    element_length: float = 100.0     # seconds of data per batch element
    order: str = "random"             # "random" (from reference snapshots) or "sequential" (carry-over)
    batch_size: int = 0               # elements per optimizer step; 0: all elements at once
    step_size: float | None = None    # default: the FMU's DefaultExperiment stepSize
    solver: str = "euler"
    learning_rate: float = 3e-3
    optimizer: str = "adam"           # "adam" (one step per batch) or "lbfgs" (full batch, line search)
    processing_step_factor: float = 0.1   # step size of the pre-/post-processing relative to the ANN's (0: fixed)
    decay: float = 0.95               # step-size factor per epoch
    backtrack: bool = True            # an epoch worse than the best: back to the best, half the step size
    keep_best: bool = True            # end with the parameters of the lowest epoch loss
    nipt_iterations: int = 400
    ccpt_iterations: int = 0          # 0: no collocation pre-training
    ccpt_window: float = 1.0          # seconds of data per local derivative fit
    warm_start: bool = False          # fit the ANN to the collocation estimate (L-BFGS) before training
    warm_start_iterations: int = 300  # L-BFGS iterations of the warm start
    warm_start_target: str = "pointwise"  # "pointwise": local slopes; "integral": window increments (warm_start.py)
    integral_window: float = 0.5      # seconds per window of the integral target
    last_layer_simulations: int = 0   # after the training: simulations of the last layer's refinement (last_layer.py)
    # No training through the solver (nor the last layer's refinement) when, after the warm start, every
    # loss signal's MSE over the training run (the engine, from its start) is at most this factor of
    # its noise variance (the data's spread): its steps could fit only the noise. None: always train.
    floor_factor: float | None = None
    time_budget: float | None = None  # seconds for the whole training call
    seed: int = 0
    loss_signals: list[str] | None = None  # default: every measured signal
    loss_scale: str = "plain"         # each signal's MSE divided by "plain": the plain FMU's, "noise": its noise variance
    # Measured outputs that the hybrid sets equal to a corrected derivative, {output: derivative}
    # (a power whose integral is an energy state): the training reads them from the hybrid's
    # derivative, as the exported hybrid does. Read from the FMU they stay the plain model's, and
    # the loss on them can only be lowered through the other channels (on the DC drive's two
    # effects the friction grew to draw the missing power through the current, and the winding
    # heated by as much too much as the plain model heats too little).
    aliases: dict[str, str] = field(default_factory=dict)
    sensor_lag: float | None = None   # s, first-order lag of the sensors, applied to the simulated signals
                                      # before they meet the data; None: the data's sidecar (synth), else 0
    checkpoint: str | None = None     # default: <output>.ckpt when an output is given
    resume: bool = False
    progress: bool = True
    threads: int | None = 1           # torch intra-op threads (tiny tensors: 1 is fastest)
