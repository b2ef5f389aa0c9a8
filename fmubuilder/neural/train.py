"""Training a NeuralFMU on measured data (Thummerer et al.'s NeuralFMU workflow, adapted; the
choices in numbers: docs/MEASUREMENTS.md, "How the training gets there").
1. Reference simulation of the plain FMU over the data, with the same fixed-step solver: the pre-/
   post-processing scales and the batch elements' starts. The data hold no controller states, so an
   element starts from the FMU state the reference saved there, measured states set to their
   measured values (measured_initial_states). Unmeasured states of the plain FMU can be far from the
   truth (an integral compensating an unmodelled load), so after pre-training the starts are captured
   again from the hybrid, and during training each element's final FMU state starts the next one
   (carry-over). An FMU that cannot save its state gets the same starts, up to rounding, by replaying
   the runs that reached them (solve.Replay), but no gradient through its discrete states at events.
2. Neutral-initialisation pre-training (NIPT): the ANN fitted to leave the hybrid unchanged.
3. Optional collocation pre-training (CCPT) of channels der(s) with s measured: the ANN fitted,
   without the solver, to the measured derivative of s minus the FMU's; the warm start
   (warm_start.py) fits that target, and the same difference along the plain model's own run,
   with L-BFGS and keeps the fit only if it lowers the training loss; then it fits the ANN's last
   layer through the simulation (last_layer.py), which sees what the estimates miss (a controller
   that hides the effect from the measured derivative, the estimate's noise).
4. Training on elements (default 100 s) simulated side by side; the loss is the mean over the
   measured signals of their MSE (weighted by <signal>_std columns), the model seen through the
   sensors' lag (`sensor_lag`), divided by the plain FMU's (or, loss_scale "noise", by each signal's
   noise variance: noise_scale). Adam with step-size decay per epoch and
   rewinds after a worse epoch (Trainer._keep_best), or one L-BFGS step over all elements per epoch;
   the work is `epochs`, or with `budget` loss evaluations spent exactly (Trainer.fit). The
   parameters of the lowest loss, or with `validation` data of the best validation score (scored at
   the start, after the warm start, after every epoch and every step a last-layer search keeps), are kept.
   Fixed seeds, a time budget, a checkpoint after every epoch, and resume.
   Then, with `last_layer_simulations`, the ANN's last layer refined through the engine by
   Levenberg-Marquardt (last_layer.py). With `floor_factor` neither runs where the hybrid after the
   warm start already lies at the noise floor on every loss signal (Trainer._at_noise_floor).
5. Errors before (plain FMU) and after (trained hybrid) over the whole data, with the engine.
"""
from __future__ import annotations

import contextlib
import copy
import dataclasses
import json
import math
import random
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from ..errors import FmuBuilderError
from ..data import MeasuredData, load_data, sensor_reading
from ..files import refuse_existing, write_atomically
from ..progress import Bar
from ..score import floors_of, validation_score
from .core_gradient import simulate_for_loss, simulate_without_gradient
from .io import save_neural_fmu
from .model import NeuralFMU
from .sensor import sensor_grid
from .settings import TrainSettings
from .solve import ElementStart, simulate
from .system import simulate_hybrid
from .topology import TopologyConfig


@dataclass
class Validation:
    """Held-out samples that pick the parameters the training ends with: the samples of `data`
    within `window` (the model is simulated over the whole run, from its start)."""
    data: MeasuredData
    window: tuple[float, float]
    start_values: dict = field(default_factory=dict)


@dataclass
class TrainingResult:
    model: NeuralFMU
    metrics: dict
    history: list[dict] = field(default_factory=list)


# ------------------------------------------------------------------------------------------
# entry point

def train_neural_fmu(fmu: str | Path, data: str | Path | MeasuredData, *, targets: Sequence[str],
                     inputs: Sequence[str], start_values: dict | None = None, topology: str = "residual",
                     hidden: Sequence[int] = (16, 16), activation: str = "tanh", parameters: Sequence[str] = (),
                     base_terms: Sequence[dict] = (), channel_inputs: Sequence[Sequence[str]] = (),
                     settings: TrainSettings | None = None, output: str | Path | None = None,
                     metrics_path: str | Path | None = None, force: bool = False,
                     test_data: str | Path | MeasuredData | None = None, validation: Validation | None = None,
                     on_epoch=None, **overrides) -> TrainingResult:
    """Train a NeuralFMU around `fmu` on `data` (see the module docstring).

    targets: derivative channels, e.g. ["der(speed)"]; inputs: FMU variables fed to the ANN;
    topology: "residual" (on the VLDM about ten times faster per epoch) or "gates"; base_terms: a
    fitted term the residual ANN starts from and adds to (base_term.py); channel_inputs: per target
    the inputs its correction reads (empty: all of them; topology.py); settings or keyword
    overrides of TrainSettings (epochs=...); validation: see Validation and Trainer.validation_score.
    Writes the model to `output` and the errors to `metrics_path` (JSON) when given.
    on_epoch(epoch, trainer) is called after every epoch; returning True stops the training.
    """
    settings = _settings(settings, overrides)
    started = time.perf_counter()
    _check_outputs(output, metrics_path, force)
    checkpoint = _checkpoint_path(settings, output)
    if settings.resume and (checkpoint is None or not checkpoint.is_file()):
        raise FmuBuilderError(f"no checkpoint {checkpoint} to resume from; train without --resume "
                              "(with --force to replace the earlier output)")
    if checkpoint is not None and not settings.resume:
        refuse_existing(checkpoint, force)    # another training's state, kept for its --resume
    _seed(settings.seed)
    if settings.threads:
        torch.set_num_threads(settings.threads)
    config = TopologyConfig(channels=list(targets), inputs=list(inputs), hidden=list(hidden),
                            activation=activation, kind=topology, parameters=list(parameters),
                            base_terms=[dict(t) for t in base_terms],
                            channel_inputs=[list(names) for names in channel_inputs])
    if not isinstance(data, MeasuredData):     # a data file: its sidecar's start values, under the given ones
        from ..fmi import read_model_info
        data = load_data(data, read_model_info(fmu))
        start_values = {**data.start_values, **(start_values or {})}
    model = NeuralFMU(fmu, config, start_values)
    try:
        if settings.sensor_lag is None:
            settings.sensor_lag = data.sensor_lag
        trainer = Trainer(model, data, settings, started, validation)
        trainer.prepare()
        before = trainer.errors(data, plain=True)
        trainer.fit(checkpoint=checkpoint, on_epoch=on_epoch)
        metrics = {"errors": {"before": before, "after": trainer.errors(data)},
                   "seconds": time.perf_counter() - started, "epochs": trainer.epochs_done,
                   "epochs_planned": settings.epochs if settings.budget is None else None,
                   "budget": settings.budget, "cut_short_by_time_budget": trainer.cut_short,
                   "loss": trainer.history[-1]["loss"] if trainer.history else None,
                   "settings": asdict(settings), "element_start_replays": dict(model.replays),
                   "loss_evaluations": trainer.loss_evaluations, "warm_start": trainer.warm_start,
                   "last_layer": trainer.last_layer, "free_start_offsets": trainer.free_offsets,
                   "at_noise_floor": trainer.at_floor,
                   "validation": trainer.validation_summary()}
        if test_data is not None:
            test = test_data if isinstance(test_data, MeasuredData) else load_data(test_data, model.info)
            metrics["test_errors"] = {"before": trainer.errors(test, test.start_values, plain=True),
                                      "after": trainer.errors(test, test.start_values)}
        if output is not None:
            save_neural_fmu(model, output, metadata={"data": data.source, "metrics": metrics}, force=True)
        if metrics_path is not None:
            write_atomically(Path(metrics_path), json.dumps(metrics, indent=2, default=float) + "\n")
        return TrainingResult(model, metrics, trainer.history)
    except BaseException:
        model.close()
        raise


def _settings(settings: TrainSettings | None, overrides: dict) -> TrainSettings:
    unknown = set(overrides) - set(TrainSettings.__dataclass_fields__)
    if unknown:
        raise FmuBuilderError(f"unknown training settings {sorted(unknown)}; known: {sorted(TrainSettings.__dataclass_fields__)}")
    settings = dataclasses.replace(settings or TrainSettings(), **overrides)
    for name, what, choices in (("optimizer", "optimizer", ("adam", "lbfgs")),
                                ("warm_start_target", "warm start target", ("pointwise", "integral")),
                                ("order", "element order", ("random", "sequential")),
                                ("loss_scale", "loss scale", ("plain", "noise"))):
        if getattr(settings, name) not in choices:
            raise FmuBuilderError(f"unknown {what} '{getattr(settings, name)}': use {' or '.join(choices)}")
    if not settings.integral_window > 0:
        raise FmuBuilderError(f"the integral window must be positive seconds, got {settings.integral_window}")
    if settings.epochs < 0:
        raise FmuBuilderError(f"epochs must be >= 0, got {settings.epochs}")
    if settings.budget is not None and settings.budget < 0:
        raise FmuBuilderError(f"the budget must be >= 0 loss evaluations, got {settings.budget}")
    if not settings.element_length > 0:
        raise FmuBuilderError(f"element length must be positive, got {settings.element_length}")
    if settings.sensor_lag is not None and not settings.sensor_lag >= 0:
        raise FmuBuilderError(f"sensor lag must be >= 0 seconds, got {settings.sensor_lag}")
    if settings.time_budget is not None and not settings.time_budget > 0:
        raise FmuBuilderError(f"time budget must be positive seconds, got {settings.time_budget}")
    return settings


def _check_outputs(output, metrics_path, force: bool) -> None:
    for path in (output, metrics_path):
        if path is None:
            continue
        path = refuse_existing(path, force)
        if not path.parent.is_dir():
            raise FmuBuilderError(f"cannot write {path}: directory {path.parent} does not exist; create it first")


def _checkpoint_path(settings: TrainSettings, output) -> Path | None:
    if settings.checkpoint:
        return Path(settings.checkpoint)
    return Path(str(output) + ".ckpt") if output is not None else None


def _seed(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


# ------------------------------------------------------------------------------------------
# errors of a model on data

def evaluate(model: NeuralFMU, data: MeasuredData, step: float, solver: str = "euler",
             start_values: dict | None = None, plain: bool = False, sensor_lag: float = 0.0,
             aliases: dict | None = None) -> dict:
    """{signal: {"mse", "max_abs", "final"}} of the hybrid (or, with plain, of the FMU alone: the ANN
    gated off, trained FMU parameters kept) over the whole data (see simulate_over), the model seen
    through sensors with a first-order lag; aliases: TrainSettings.aliases."""
    result = simulate_over(model, data, step, solver, start_values, plain, aliases)
    return data_errors(data, result, sensor_lag, aliases)


def data_errors(data: MeasuredData, result, sensor_lag: float = 0.0, aliases: dict | None = None) -> dict:
    """{signal: {"mse", "max_abs", "final"}} of an engine result against the data; a signal in
    `aliases` is read from the derivative it names."""
    errors = {}
    aliases = aliases or {}
    for name in data.signals:
        diff = predicted_at_samples(data, result, name, sensor_lag, aliases) - data.signals[name]
        errors[name] = {"mse": float(np.mean(diff ** 2)), "max_abs": float(np.max(np.abs(diff))),
                        "final": float(abs(diff[-1]))}
    return errors


def predicted_at_samples(data: MeasuredData, result, name: str, sensor_lag: float = 0.0,
                         aliases: dict | None = None) -> np.ndarray:
    """What the sensor of signal `name` shows at the data's samples: the engine result's value (or
    the derivative it is an alias of) through the sensors' first-order lag, the settled value at an
    event's time (as the choice's scoring reads it: hybridize.evaluate)."""
    return sensor_reading(result.time, result[(aliases or {}).get(name, name)], data.time, sensor_lag)


def simulate_over(model: NeuralFMU, data: MeasuredData, step: float, solver: str = "euler",
                  start_values: dict | None = None, plain: bool = False, aliases: dict | None = None,
                  record: Sequence[str] = ()):
    """Engine result (with its statistics) of the hybrid, or with plain of the FMU alone, over the
    data's span, recording the measured signals (and the derivatives `aliases` reads them from, and
    `record`) every step and on both sides of every event (a sample between two steps must not
    interpolate across a jump); measured states start where the data's first samples put them
    (measured_initial_states), the data's inputs drive the FMU."""
    original = model.start_values
    model.start_values = {**original, **measured_initial_states(model, data), **(start_values or {})}
    try:
        with (model.topology.ann_off(fmu_gate_one=True) if plain else contextlib.nullcontext()):
            variables = list(dict.fromkeys([*data.signals, *(aliases or {}).values(), *record]))
            return simulate_hybrid(model, start_time=data.start, stop_time=data.stop, variables=variables,
                                   solver=solver, step_size=step, output_interval=step,
                                   inputs=data.input_signals(model.info), record_events=True)
    finally:
        model.start_values = original


def measured_initial_states(model: NeuralFMU, data: MeasuredData, t0: float | None = None,
                            model_values: dict | None = None, sensor_lag: float = 0.0,
                            model_runs: dict | None = None) -> dict:
    """Values of the measured continuous states to start at t0 (default: the data's start) with: the
    model's own value (its start value, or `model_values` along a run) where the first samples of
    data agree with it, else a line fitted through them (see MeasuredData.start_estimate). A sensor
    with a first-order lag shows a smoothly moving state `sensor_lag` late: the samples from
    t0 + sensor_lag tell the state at t0. `model_runs` ({state: (times, values)} of the run
    `model_values` lie on) give the course the samples are compared with."""
    t0 = data.start if t0 is None else t0
    own = model_values if model_values is not None else {
        s: model.start_values.get(s, model.info.variable(s).start) for s in model.state_names()}
    at = min(t0 + sensor_lag, float(data.time[-1]))

    def course(state: str):
        if not model_runs or state not in model_runs:
            return None
        times, values = model_runs[state]
        return lambda t: np.interp(np.asarray(t) - sensor_lag, times, values)
    return {s: data.start_estimate(s, at, own.get(s), course(s)) for s in model.state_names() if s in data.signals}


# ------------------------------------------------------------------------------------------
# the trainer

class Trainer:
    """One training run: reference, pre-training, the epoch loop (see the module docstring)."""

    def __init__(self, model: NeuralFMU, data: MeasuredData, settings: TrainSettings, started: float,
                 validation: Validation | None = None):
        self.model, self.data, self.settings, self.started = model, data, settings, started
        self.validation = validation
        self._validation_plain: dict | None = None     # the plain FMU's errors on the validation window
        self._validation_floors: dict | None = None
        self.validation_best: tuple[float, int, dict, str] | None = None   # (score, epoch, parameters, stage)
        self.validation_start: float | None = None                     # the score before training
        self._last_scored: tuple[dict, float] | None = None             # (parameters, score) scored last
        self.step = float(settings.step_size or model.info.default_experiment.step_size or
                          (data.stop - data.start) / max(10 * data.time.size, 1000))
        self.loss_signals = list(settings.loss_signals or data.signals)
        for name in self.loss_signals:
            if name not in data.signals:
                raise FmuBuilderError(f"loss signal '{name}' is not a column of {data.source}; "
                                      f"choose among {', '.join(data.signals)}")
        self.scale = {name: _variance(data.signals[name]) for name in self.loss_signals}
        # what the loss reads for each loss signal: the signal, or the derivative it is an alias of
        self.recorded = [settings.aliases.get(name, name) for name in self.loss_signals]
        self.inputs = data.input_signals(self.model.info)
        self.history: list[dict] = []
        self.epochs_done = 0
        self.loss_evaluations = 0   # forward and backward passes through the solver, over a batch
        self.cut_short = False     # the time budget ended the training before its epochs
        self.elements: list[_Element] = []
        self.free_offsets: list[str] = []   # states whose element starts the loss fits (see _free_offsets)
        self.reference = None
        self.warm_start: dict | None = None   # what the warm start did (see warm_start.py)
        self.last_layer: dict | None = None   # what the last layer's refinement did (see last_layer.py)
        self.at_floor: dict | None = None     # {"factor", "ratios": {signal: MSE / noise variance}}: not trained there
        self.best_loss, self.best_state, self._best = math.inf, None, None   # see _keep_best
        self._lbfgs_seen: list = []   # ((parameters, element starts), loss, gradients) of recent L-BFGS evaluations
        self._lbfgs_tried: list = []  # (parameters, loss) of the points the current L-BFGS step asked for

    @property
    def sensor_lag(self) -> float:
        return self.settings.sensor_lag or 0.0

    def elapsed(self) -> float:
        return time.perf_counter() - self.started

    def out_of_time(self) -> bool:
        """Whether the wall-clock cap (time_budget) is used up; the work itself is counted in epochs,
        so the cap changes the result only when it cuts the training short, which it records."""
        budget = self.settings.time_budget
        if budget is not None and self.elapsed() > budget:
            self.cut_short = True
        return self.cut_short

    # -- preparation --------------------------------------------------------------------------
    def prepare(self) -> None:
        starts = plan_elements(self.data.start, self.data.stop, self.settings.element_length, self.step)
        self.element_duration = min(self.settings.element_length, self.data.stop - self.data.start)
        self.reference = self._reference(starts)
        self.model.topology.initialise_scaling(*self.reference_samples())
        self.track_validation(0, "start")      # the plain FMU, or the base term alone
        if self.settings.nipt_iterations and self.model.topology.has_ann and self.model.config.kind == "gates":
            neutral_pretraining(self.model, *self.reference_samples(), iterations=self.settings.nipt_iterations)
        if self.settings.ccpt_iterations and self.model.topology.has_ann:
            collocation_pretraining(self)
        if self.settings.warm_start and self.model.topology.has_ann:
            from .warm_start import warm_start
            self.warm_start = warm_start(self)
            self.track_validation(0, "warm start")
        if not self.model.topology.is_neutral():
            self._capture_starts(plain=False)

    def _reference(self, starts: list[float]):
        """Plain-FMU simulation over the data; FMU states saved at the element starts."""
        self.start_times = starts
        ref = self._capture_starts(plain=True)
        for index, element_start in enumerate(self._captured):
            self.elements.append(_Element(index, element_start, self._targets(element_start.t0),
                                          self._sensor_start(element_start.t0)))
        self.free_offsets = self._free_offsets()
        self.scale = self._reference_scale()
        return ref

    def _free_offsets(self) -> list[str]:
        """Measured states in the loss that nothing else depends on (an energy integrating a power).
        An element starts such a state where a few noisy samples put it (on the VLDM a line through
        them missed by several times the noise where the power changes), and the whole element then
        carries the offset, which the loss charged to the model (the truth's own training loss on the
        energy 10.7 times the noise variance). The loss takes the offset out instead, the
        least-squares start of the element (_residuals). Found by simulating the first element again
        with the state shifted, the ANN switched off (so it may not read the state; a base term reads
        ANN inputs only): every other state, derivative and loss signal must come out exactly equal.
        The whole element, not its first second: a state may act only through a later event (a ball
        dropped from 10 m moves nothing else until its impact at 1.43 s). Over the VLDM's 100 s
        elements that costs two simulations of about 2 s; the whole training run would cost 37 s."""
        candidates = [s for s in self._measured_states()
                      if s in self.loss_signals and s not in self.model.config.inputs]
        first = self.elements[0].start if self.elements else None
        if not candidates or first is None or first.fmu_state is None or first.states is None:
            return []
        names = self.model.state_names()
        watched = list(dict.fromkeys(names + [v.name for v in self.model.info.derivatives] + self.recorded))
        duration = self.element_duration

        def run(shifted: str | None) -> torch.Tensor:
            states = dict(first.states)
            if shifted is not None:
                states[shifted] = states.get(shifted, 0.0) + max(1.0, abs(states.get(shifted, 0.0))) * 1e-3
            start = ElementStart(first.t0, first.fmu_state, first.next_event_time, states)
            with torch.no_grad(), self.model.topology.ann_off():
                return simulate(self.model, duration, self.step, starts=[start], record=watched,
                                solver=self.settings.solver, inputs=self.inputs).values[:, 0, :]
        base = run(None)
        free = []
        for state in candidates:
            others = [j for j, name in enumerate(watched) if name != state]
            if torch.equal(run(state)[:, others], base[:, others]):
                free.append(state)
        return free

    def _reference_scale(self) -> dict:
        """Per-signal divisor of the MSE in the loss: the plain FMU's MSE on the elements, floored at
        1e-6 of the signal's variance (a signal the FMU already matches exactly must not dominate the
        loss); with loss_scale "noise" the signal's noise variance where the data give one (see
        noise_scale). One that overflowed (values near the float range) would make every loss inf or
        nan: an error before training."""
        with torch.no_grad(), self.model.topology.ann_off():
            errors = self._signal_errors(self.elements, keep_final_state=False)
        scale = {name: max(float(errors[name]), 1e-6 * self.scale[name]) for name in self.loss_signals}
        broken = [name for name, value in scale.items() if not math.isfinite(value)]
        if broken:
            raise FmuBuilderError(
                f"the plain FMU's error on {', '.join(broken)} in {self.data.source} is not a finite number "
                "(values far outside the float range, or a simulation that diverged); check the data's values "
                "and units")
        if self.settings.loss_scale == "noise":
            scale = noise_scale(self.data, scale)
        return scale

    def _capture_starts(self, plain: bool):
        """Simulate over the whole data (no gradient) and save the FMU state at each element start;
        with `plain` the ANN is switched off (gate_ann = 0)."""
        model, data = self.model, self.data
        grid_index = [int(round((s - data.start) / self.step)) for s in self.start_times]
        first = ElementStart(data.start, states=measured_initial_states(model, data))
        recorded = list(dict.fromkeys(model.config.inputs + model.config.channels + list(data.signals)))
        with torch.no_grad(), (model.topology.ann_off() if plain else contextlib.nullcontext()):
            run = simulate_without_gradient(model, data.stop - data.start, self.step, starts=[first], record=recorded,
                                            solver=self.settings.solver, inputs=self.inputs, capture=grid_index)
        measured = self._measured_states()
        courses = {s: (data.start + run.times, run.numpy(s)[:, 0]) for s in measured}
        self._captured = [self._with_measured_states(run.captured[k][0], {s: float(run.numpy(s)[k, 0]) for s in measured},
                                                     courses)
                          for k in grid_index]
        for element, start in zip(self.elements, self._captured):
            element.start = start
        return run

    def _measured_states(self) -> list[str]:
        return [s for s in self.model.state_names() if s in self.data.signals]

    def _with_measured_states(self, start: ElementStart, along_run: dict, courses: dict | None = None) -> ElementStart:
        """The element starts at the measured states, or at the run's (`along_run`; `courses`: the
        run's course over the data, see measured_initial_states) where the data agree with them."""
        start.states = measured_initial_states(self.model, self.data, start.t0, along_run,
                                               sensor_lag=self.sensor_lag, model_runs=courses)
        return start

    def reference_samples(self) -> tuple[np.ndarray, np.ndarray]:
        """(ANN inputs [N, n_in], channels [N, C]) along the reference run (the plain model's)."""
        def columns(names: list[str]) -> np.ndarray:
            return np.stack([self.reference.numpy(name)[:, 0] for name in names], axis=1) if names else np.zeros((0, 0))
        return columns(self.model.config.inputs), columns(self.model.config.channels)

    def _targets(self, t0: float) -> dict:
        """Data points of the element starting at t0: grid positions and measured values per signal."""
        data, h = self.data, self.step
        t1 = t0 + self.element_duration
        inside = (data.time >= t0) & (data.time <= t1 + 1e-9 * max(1.0, abs(t1)))
        times = data.time[inside]
        position = (times - t0) / h
        K = int(math.ceil(self.element_duration / h - 1e-9))
        k0 = np.clip(np.floor(position).astype(int), 0, K - 1)
        frac = np.clip(position - k0, 0.0, 1.0)
        targets = {}
        for name in self.loss_signals:
            weight = data.weights(name)[inside]
            targets[name] = (torch.from_numpy(k0), torch.from_numpy(frac),
                             torch.from_numpy(np.asarray(data.signals[name], dtype=float)[inside]),
                             torch.from_numpy(weight))
        return targets

    def _sensor_start(self, t0: float) -> dict:
        """{signal: what its sensor shows at t0} (a line through the first samples): a lagging sensor
        enters an element showing where the signal was, not where it is."""
        return {name: self.data.start_estimate(name, t0) for name in self.loss_signals}

    def errors(self, data: MeasuredData, start_values: dict | None = None, plain: bool = False) -> dict:
        """evaluate() at the training's step, solver and sensor lag."""
        return evaluate(self.model, data, self.step, self.settings.solver, start_values, plain, self.sensor_lag,
                        self.settings.aliases)

    # -- the epoch loop -------------------------------------------------------------------------
    def fit(self, checkpoint: Path | None = None, on_epoch=None) -> None:
        """The epochs, one optimizer step per batch, until `epochs` of them; with a `budget`, until
        that many loss evaluations instead (an Adam step costs one, an L-BFGS step what its line
        search takes, at most LBFGS_LINE_SEARCH_EVALUATIONS). The count of work, not of steps, is
        what makes the optimizers comparable and the result independent of the machine's load."""
        settings, model = self.settings, self.model
        parameters = [p for p in model.topology.parameters() if p.requires_grad]
        if not parameters or self._planned_work() == 0 or self._at_noise_floor():
            self.restore_best()
            return
        state = self._read_checkpoint(checkpoint) if settings.resume and checkpoint is not None and checkpoint.is_file() else None
        first_epoch = self._resume_from(state) if state is not None else 0
        optimizer = self._optimizer(parameters, lbfgs=settings.optimizer == "lbfgs")
        scheduler = self._scheduler(optimizer)
        if state is not None:
            optimizer.load_state_dict(state["optimizer"])
            scheduler.load_state_dict(state["scheduler"])
        batches = self._batches_per_epoch()
        # counted in batches or loss evaluations (known beforehand); a time budget or on_epoch may stop it early, with a note
        bar = Bar(self._planned_work(), "training", "evaluation" if settings.budget is not None else "batch",
                  initial=self.loss_evaluations if settings.budget is not None else first_epoch * batches,
                  show=settings.progress)
        rng = np.random.default_rng(settings.seed + first_epoch)
        try:
            epoch = first_epoch
            while not self._work_done(epoch):
                if self.out_of_time():
                    bar.stop("time budget used up")
                    break
                before = (_copy_state(model.topology), copy.deepcopy(optimizer.state_dict()),
                          [element.start for element in self.elements])
                evaluations = self.loss_evaluations
                losses = self._epoch(rng, optimizer, bar, epoch)
                if not losses:
                    bar.stop("time budget used up")
                    break
                converged = self.loss_evaluations == evaluations   # an L-BFGS step that found nothing to try
                scheduler.step()
                loss = float(np.mean(losses))
                rewind = batches == 1 and isinstance(optimizer, torch.optim.Adam)   # L-BFGS has its line search
                backtracked = self._keep_best(loss, before, optimizer, rewind=rewind)
                epoch = self.epochs_done = epoch + 1
                self.history.append({"epoch": epoch, "loss": loss, "seconds": self.elapsed(),
                                     "lr": optimizer.param_groups[0]["lr"], "backtracked": backtracked,
                                     "loss_evaluations": self.loss_evaluations,
                                     "validation": self.track_validation(epoch)})
                if checkpoint is not None:
                    self._save_checkpoint(checkpoint, optimizer, scheduler, epoch)
                if on_epoch is not None and on_epoch(epoch, self):
                    bar.stop(f"ended by the caller after epoch {epoch}")
                    break
                if converged and settings.budget is not None:
                    bar.stop("L-BFGS converged: its gradient vanished")
                    break
        except KeyboardInterrupt:
            bar.stop("interrupted")
            raise
        finally:
            bar.close()
        if isinstance(optimizer, torch.optim.LBFGS):
            self._keep_last_lbfgs_point()
        self.restore_best()
        self._refine_last_layer()

    def _at_noise_floor(self) -> bool:
        """Whether every loss signal's MSE over the training run, from its start, is at most
        settings.floor_factor times its noise variance (one engine simulation); then records the
        ratios in `at_floor`. On the demo the warm start leaves speed, power and energy at 0.970,
        1.07 and 0.970 times their noise variance (the factor: 1.11), and the five loss evaluations
        after it (two L-BFGS steps) ended at the warm start: none scored better on the validation
        data."""
        factor = self.settings.floor_factor
        noise = {name: self.data.noise_variance(name) for name in self.loss_signals}
        if factor is None or not all(v is not None and v > 0 for v in noise.values()):
            return False
        try:
            differences = self.engine_differences()
        except FmuBuilderError:
            return False
        ratios = {name: float(np.mean(differences[name] ** 2)) / noise[name] for name in self.loss_signals}
        if not all(math.isfinite(r) and r <= factor for r in ratios.values()):
            return False
        self.at_floor = {"factor": factor, "ratios": ratios}
        return True

    def engine_differences(self) -> dict:
        """{loss signal: the hybrid's value seen through the sensor - the measured, at the samples}
        over the training data, simulated by the engine (no gradient) from the data's start."""
        aliases = self.settings.aliases
        result = simulate_over(self.model, self.data, self.step, self.settings.solver, aliases=aliases)
        return {name: predicted_at_samples(self.data, result, name, self.sensor_lag, aliases) - self.data.signals[name]
                for name in self.loss_signals}

    def _refine_last_layer(self) -> None:
        """Levenberg-Marquardt on the ANN's last layer (last_layer.py); with validation data each of
        its steps is scored there too, and one kept only if it is the best."""
        if not self.settings.last_layer_simulations or self.cut_short:
            return
        from .last_layer import refine_last_layer
        self.last_layer = refine_last_layer(self, self.settings.last_layer_simulations,
                                            stage=(self.epochs_done + 1, "last layer"))
        if self.last_layer is not None and self.validation is not None:
            self.last_layer["validation"] = self.track_validation(self.epochs_done + 1, "last layer")
            self.last_layer["kept"] &= self.validation_best[1] == self.epochs_done + 1
            self.restore_best()

    def _planned_work(self) -> int:
        """The bar's total: loss evaluations with a budget, else batches."""
        budget = self.settings.budget
        return budget if budget is not None else self.settings.epochs * self._batches_per_epoch()

    def _work_done(self, epoch: int) -> bool:
        return self._evaluations_left() <= 0 if self.settings.budget is not None else epoch >= self.settings.epochs

    def _evaluations_left(self) -> float:
        budget = self.settings.budget
        return math.inf if budget is None else budget - self.loss_evaluations

    def _scheduler(self, optimizer):
        decay = self.settings.decay if isinstance(optimizer, torch.optim.Adam) else 1.0
        return torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=decay)

    def _status(self, epoch: int) -> str:
        if self.settings.budget is not None:
            return f"{self.loss_evaluations}/{self.settings.budget} evaluations"
        return f"epoch {epoch + 1}/{self.settings.epochs}"

    def _epoch(self, rng, optimizer, bar, epoch: int) -> list[float]:
        """One pass over the elements, one optimizer step per batch; the batches' losses."""
        if isinstance(optimizer, torch.optim.LBFGS):
            return self._lbfgs_step(optimizer, bar, epoch)
        losses = []
        for batch in self._epoch_batches(rng):
            if self.out_of_time() or self._evaluations_left() <= 0:
                break
            optimizer.zero_grad()
            loss = self.batch_loss(batch)
            loss.backward()
            optimizer.step()
            self.loss_evaluations += 1
            losses.append(float(loss.detach()))
            bar.advance(1, at=self._status(epoch), loss=f"{losses[-1]:.4g}")
        return losses

    def _lbfgs_step(self, optimizer, bar, epoch: int) -> list[float]:
        """One L-BFGS iteration over all elements at once; its line search evaluates the loss a few
        times on the same element starts (no carry-over: the loss must be one function). Returns
        the loss at the parameters the step started from. With a budget the line search gets what
        is left of it; should it ask for more, the step ends at the lowest loss it has evaluated."""
        parameters = optimizer.param_groups[0]["params"]
        start_is_known = self._lbfgs_known(_flat(parameters)) is not None
        left = self._evaluations_left()
        optimizer.param_groups[0]["max_eval"] = int(min(LBFGS_LINE_SEARCH_EVALUATIONS,
                                                        max(left - (0 if start_is_known else 1), 1)))
        spent = self.loss_evaluations
        self._lbfgs_tried = []
        try:
            loss = float(optimizer.step(self._lbfgs_closure(optimizer)))
        except _BudgetSpent:
            loss = float(self._lbfgs_tried[0][1])
            best = min(self._lbfgs_tried, key=lambda tried: float(tried[1]))
            torch.nn.utils.vector_to_parameters(best[0], parameters)
        if bar is not None:
            bar.advance(self.loss_evaluations - spent if self.settings.budget is not None else 1,
                        at=self._status(epoch), loss=f"{loss:.4g}")
        return [loss] if math.isfinite(loss) else []

    def _lbfgs_known(self, parameters: torch.Tensor):
        """The remembered evaluation (point, loss, gradients) at these parameters and the current element starts."""
        point = (parameters, [e.start for e in self.elements])
        return next((seen for seen in reversed(self._lbfgs_seen) if _same_point(seen[0], point)), None)

    def _keep_last_lbfgs_point(self) -> None:
        """The epoch losses are measured at each step's start, so the point the last step reached
        would be lost; its loss is known from its line search: keep it if it is the lowest."""
        if not self.settings.keep_best or self.best_state is None:
            return
        parameters = network_parameters(self.model.topology, [p for p in self.model.topology.parameters()
                                                              if p.requires_grad])
        seen = self._lbfgs_known(_flat(parameters))
        if seen is not None and float(seen[1]) < self.best_loss:
            self.best_loss, self.best_state = float(seen[1]), _copy_state(self.model.topology)

    def _lbfgs_closure(self, optimizer):
        """The loss and its gradient for torch's L-BFGS, with three guards:
        * an evaluation at a point evaluated before (the point where the previous step's line search
          ended, with which each step() starts, or a point its zoom went back to) is given back
          instead of simulated again (a whole pass), as long as the parameters and the element
          starts are the same objects' same values;
        * a trial point whose simulation diverged (loss inf or nan) reports an infinite loss and a
          nan gradient: the strong Wolfe search then brackets it and bisects back towards the
          start. A nan loss compares false with everything and was accepted as the step;
        * an evaluation beyond the budget raises _BudgetSpent (see _lbfgs_step)."""
        parameters = optimizer.param_groups[0]["params"]

        def closure():
            point = (_flat(parameters), [e.start for e in self.elements])
            remembered = self._lbfgs_known(point[0])
            if remembered is not None:
                for p, gradient in zip(parameters, remembered[2]):
                    p.grad = gradient.clone()
                self._lbfgs_tried.append((point[0], remembered[1]))
                return remembered[1].clone()
            if self._evaluations_left() <= 0:
                raise _BudgetSpent
            optimizer.zero_grad()
            loss = self.batch_loss(self.elements, carry=False)
            self.loss_evaluations += 1
            if torch.isfinite(loss):
                loss.backward()
            else:
                loss = torch.tensor(math.inf, dtype=loss.dtype)
                for p in parameters:
                    p.grad = torch.full_like(p, math.nan)
            loss = loss.detach()
            self._lbfgs_tried.append((point[0], loss))
            self._lbfgs_seen.append((point, loss, [p.grad.detach().clone() if p.grad is not None else torch.zeros_like(p)
                                                   for p in parameters]))
            del self._lbfgs_seen[:-2 * LBFGS_LINE_SEARCH_EVALUATIONS]
            return loss
        return closure

    def _optimizer(self, parameters, lbfgs: bool):
        """Adam, the pre-/post-processing at processing_step_factor times the step size (why:
        docs/MEASUREMENTS.md, "How the training gets there"); or L-BFGS on the network alone."""
        if lbfgs:
            parameters = network_parameters(self.model.topology, parameters)
            # max_eval: torch's default (max_iter * 5 // 4 = 1) leaves its line search no evaluation
            # beyond the first trial, so a step that overshot was taken back to t = 0 and the
            # next one, without a curvature pair, tried the raw gradient at t = 1.
            return torch.optim.LBFGS(parameters, lr=1.0, max_iter=1, max_eval=LBFGS_LINE_SEARCH_EVALUATIONS,
                                     history_size=10, line_search_fn="strong_wolfe")
        network = network_parameters(self.model.topology, parameters)
        in_network = {id(p) for p in network}
        slow = [p for p in parameters if id(p) not in in_network]
        groups = [{"params": network}]
        if slow and self.settings.processing_step_factor > 0:
            groups.append({"params": slow, "lr": self.settings.learning_rate * self.settings.processing_step_factor})
        return torch.optim.Adam(groups, lr=self.settings.learning_rate)

    def _keep_best(self, loss: float, before: tuple, optimizer, rewind: bool) -> bool:
        """Track the parameters with the lowest epoch loss (those at the epoch's start). With
        `backtrack` and `rewind` (one batch per epoch: elsewhere the loss mixes parameters and
        elements), an epoch worse than the best rewinds to the best epoch (parameters, Adam's
        moments, element starts) and halves the step size: Adam's steps do not shrink near a
        minimum, so it overshoots and oscillates. Returns whether it rewound."""
        if loss <= self.best_loss:     # equal: the best parameters measured again after a rewind
            self.best_loss, self._best = loss, before
            self.best_state = before[0]
            return False
        if loss <= self.best_loss * (1.0 + REWIND_TOLERANCE):
            return False
        if not (self.settings.backtrack and rewind) or self._best is None:
            return False
        parameters, optimizer_state, starts = self._best
        learning_rates = [group["lr"] * 0.5 for group in optimizer.param_groups]
        self.model.topology.load_state_dict(parameters)
        optimizer.load_state_dict(optimizer_state)
        for group, learning_rate in zip(optimizer.param_groups, learning_rates):
            group["lr"] = learning_rate
        for element, start in zip(self.elements, starts):
            element.start = start
        return True

    def restore_best(self) -> None:
        """Put back the parameters with the best validation score when there are validation data,
        else those with the lowest epoch loss (see _keep_best)."""
        if self.validation_best is not None:
            self.model.topology.load_state_dict(self.validation_best[2])
        elif self.settings.keep_best and self.best_state is not None:
            self.model.topology.load_state_dict(self.best_state)

    # -- validation ---------------------------------------------------------------------------
    def validation_score(self) -> float:
        """The hybrid's score on the validation window, the model seen through the sensors: the score
        hybridize chooses its candidate by (score.validation_score: geometric mean over the signals of
        MSE / noise variance, the plain FMU's MSE for a signal without a spread column)."""
        if self._validation_plain is None:
            self._validation_plain = self._validation_errors(plain=True)
            noise = {name: self.validation.data.noise_variance(name) for name in self._validation_plain}
            self._validation_floors = floors_of(self._validation_plain, noise)
        # a neutral hybrid (a NeuralFMU's start) is the plain FMU: its run is the one just scored
        neutral = self.model.topology.is_neutral()
        errors = self._validation_plain if neutral else self._validation_errors(plain=False)
        return validation_score(errors, self._validation_floors)

    def _validation_errors(self, plain: bool) -> dict:
        part = self.validation
        aliases = self.settings.aliases
        result = simulate_over(self.model, part.data, self.step, self.settings.solver, part.start_values, plain,
                               aliases)
        return data_errors(part.data.window(*part.window), result, self.sensor_lag, aliases)

    def track_validation(self, epoch: int, stage: str = "epoch") -> float | None:
        """Score the current parameters on the validation data and keep them if they are the best;
        `stage`: what produced them ("start", "warm start", "epoch", "last layer"). Parameters just
        scored are not simulated again (the last layer's search scores its steps, and its caller
        the point the search ended at)."""
        if self.validation is None:
            return None
        state = _copy_state(self.model.topology)
        if self._last_scored is not None and _same_state(self._last_scored[0], state):
            score = self._last_scored[1]
        else:
            score = self.validation_score()
            self._last_scored = (state, score)
        if self.validation_start is None:
            self.validation_start = score
        if self.validation_best is None or score < self.validation_best[0]:
            self.validation_best = (score, epoch, state, stage)     # a copy, never changed
        return score

    def validation_summary(self) -> dict | None:
        if self.validation_best is None:
            return None
        return {"start_score": self.validation_start, "best_score": self.validation_best[0],
                "best_epoch": self.validation_best[1], "best_stage": self.validation_best[3],
                "window": list(self.validation.window)}

    def _batch_size(self) -> int:
        return 1 if self.settings.order == "sequential" else self.settings.batch_size or len(self.elements)

    def _batches_per_epoch(self) -> int:
        return math.ceil(len(self.elements) / self._batch_size())

    def _epoch_batches(self, rng):
        if self.settings.order == "sequential":
            return [[e] for e in self.elements]
        order, size = rng.permutation(len(self.elements)), self._batch_size()
        return [[self.elements[i] for i in order[j:j + size]] for j in range(0, len(order), size)]

    def batch_loss(self, batch: list["_Element"], carry: bool = True) -> torch.Tensor:
        """Loss of a batch of elements simulated side by side. With `carry`, each element's final FMU
        state becomes the start of the element after it."""
        errors = self._signal_errors(batch, keep_final_state=carry)
        return sum(errors[name] / self.scale[name] for name in self.loss_signals) / len(self.loss_signals)

    def _signal_errors(self, batch: list["_Element"], keep_final_state: bool) -> dict:
        """{signal: weighted MSE over the batch's data points} (tensors)."""
        trajectory = simulate_for_loss(self.model, self.element_duration, self.step, starts=[e.start for e in batch],
                                       record=self.recorded, solver=self.settings.solver, inputs=self.inputs,
                                       keep_final_state=keep_final_state)
        if keep_final_state:
            for position, (element, final) in enumerate(zip(batch, trajectory.final_starts)):
                if element.index + 1 < len(self.elements):
                    following = self.elements[element.index + 1]
                    if abs(final.t0 - following.start.t0) <= 1e-6 * self.step:
                        final.t0 = following.start.t0
                        names = self.model.state_names()
                        final_values = trajectory.final_states[position].detach()
                        following.start = self._with_measured_states(
                            final, {s: float(final_values[names.index(s)]) for s in self._measured_states()})
        return {name: (residual ** 2).mean() for name, residual in self._residuals(trajectory, batch).items()}

    def _residuals(self, trajectory, batch: list["_Element"]) -> dict:
        """{signal: (prediction - data) * sqrt(weight) at the batch's data points} (tensors): the run
        as its sensors show it at the samples (neural/sensor.py), as the choice's scoring reads it."""
        residuals = {}
        for j, name in enumerate(self.loss_signals):
            shown = torch.tensor([element.sensor_start[name] for element in batch], dtype=trajectory.values.dtype)
            sensor = sensor_grid(trajectory, j, self.sensor_lag, shown)
            pieces = []
            for b, element in enumerate(batch):
                k0, frac, target, weight = element.targets[name]
                residual = weight.sqrt() * (sensor.read(b, k0, frac) - target)
                if self.recorded[j] in self.free_offsets:
                    residual = self._without_start_offset(residual, weight, k0, frac)
                pieces.append(residual)
            residuals[name] = torch.cat(pieces)
        return residuals

    def _without_start_offset(self, residual: torch.Tensor, weight: torch.Tensor, k0, frac) -> torch.Tensor:
        """The residuals of a state nothing else depends on, its element started at its least-squares
        start (see _free_offsets): a start shifted by d shifts the sensor by d (1 - exp(-t / lag)),
        the sensor's own start being what the data show."""
        lag = self.sensor_lag
        elapsed = (k0.to(residual.dtype) + frac) * self.step
        basis = weight.sqrt() * (-torch.expm1(-elapsed / lag) if lag > 0.0 else torch.ones_like(elapsed))
        norm = float((basis * basis).sum())
        if norm <= 0.0:
            return residual
        return residual - basis * ((basis * residual).sum() / norm)

    def scaled_residuals(self) -> torch.Tensor:
        """All elements' residuals in one vector whose squared sum is the loss (batch_loss of all
        elements from their current starts, no carry-over), without gradient."""
        count = len(self.loss_signals)
        return torch.cat([r / math.sqrt(r.numel() * self.scale[name] * count)
                          for name, r in self._all_residuals().items()])

    def signal_losses(self) -> dict:
        """{signal: MSE over all elements from their current starts / the plain FMU's}: the loss's
        terms before their mean, without gradient."""
        return {name: float((r ** 2).mean() / self.scale[name]) for name, r in self._all_residuals().items()}

    def _all_residuals(self) -> dict:
        with torch.no_grad():
            trajectory = simulate_without_gradient(self.model, self.element_duration, self.step,
                                                   starts=[e.start for e in self.elements], record=self.recorded,
                                                   solver=self.settings.solver, inputs=self.inputs)
            return self._residuals(trajectory, self.elements)

    # -- checkpoints --------------------------------------------------------------------------
    def _save_checkpoint(self, path: Path, optimizer, scheduler, epoch: int) -> None:
        import io
        state = {"epoch": epoch, "topology": self.model.topology.state_dict(),
                 "optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(),
                 "history": self.history, "torch_rng": torch.get_rng_state(),
                 "best_loss": self.best_loss, "best_state": self.best_state,
                 "loss_evaluations": self.loss_evaluations, "config": self.model.config.to_dict()}
        buffer = io.BytesIO()
        torch.save(state, buffer)
        write_atomically(path, buffer.getvalue())

    def _read_checkpoint(self, path: Path) -> dict:
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:
            raise FmuBuilderError(f"cannot read the checkpoint {path} ({type(exc).__name__}); delete it to start over") from None
        if state.get("config") != self.model.config.to_dict():
            raise FmuBuilderError(f"the checkpoint {path} belongs to another topology; delete it or train without --resume")
        return state

    def _resume_from(self, state: dict) -> int:
        """The training's state from a checkpoint, but the optimizer's (see fit); returns the epochs done."""
        self.model.topology.load_state_dict(state["topology"])
        self.history = list(state["history"])
        self.best_loss, self.best_state = float(state.get("best_loss", math.inf)), state.get("best_state")
        torch.set_rng_state(state["torch_rng"])
        self.loss_evaluations = int(state.get("loss_evaluations", 0))
        self.epochs_done = int(state["epoch"])
        return self.epochs_done


@dataclass
class _Element:
    index: int
    start: ElementStart
    targets: dict
    sensor_start: dict        # {signal: what its sensor shows at the element's start}


# Loss evaluations the line search of one L-BFGS step may take (each a pass over all elements): its
# first trial and up to 9 more that bracket and zoom. (torch counts the step's start in max_eval;
# the closure remembers that one, see Trainer._lbfgs_closure.)
LBFGS_LINE_SEARCH_EVALUATIONS = 10

# A rise of the epoch loss up to this fraction is no overshoot: carried-over element starts move the
# loss a little even where the parameters barely do.
REWIND_TOLERANCE = 0.01


def noise_scale(data: MeasuredData, plain: dict) -> dict:
    """{signal: its noise variance} (the data's spread columns), the plain FMU's MSE for a signal
    without one (as the choice's floors, score.floors_of). Divided by the plain FMU's
    MSE, a signal the plain model already fits to a few times its noise weighs more than an
    integrator (an energy, a temperature) far off: on the DC drive's Stribeck friction the power,
    1.7 times its noise, made 0.049 of the loss and the temperature, 36 times, 0.0037, and the steps
    traded the temperature for the current and the power (bench_friction_training.py). Divided by
    the noise variance each term is what the held-out score counts."""
    scale = {}
    for name, fallback in plain.items():
        variance = data.noise_variance(name)
        scale[name] = variance if variance is not None and variance > 0 else fallback
    return scale


def plan_elements(start: float, stop: float, length: float, step: float) -> list[float]:
    """Element start times on the step grid: every `length` seconds while a whole element fits
    (at least one element; the last one ends at or before the data's end)."""
    span = stop - start
    if span <= length:
        return [start]
    count = int(math.floor(span / length + 1e-9))
    steps_per_element = int(round(length / step))
    return [start + k * steps_per_element * step for k in range(count)]


def network_parameters(topology, parameters) -> list:
    """The trained parameters less the pre-/post-processing: all that L-BFGS moves, and Adam's group
    at the full step size. The processing's units differ from the weights' by orders of magnitude:
    on the DC drive's Coulomb data the input scale's gradient was 100 times the weights', and with
    it L-BFGS spent 10 loss evaluations on a step that lowered the loss by 0.3 %."""
    processing = {id(p) for p in topology.processing_parameters()}
    return [p for p in parameters if id(p) not in processing]


class _BudgetSpent(Exception):
    """The line search asked for a loss evaluation beyond the training's budget."""


def _flat(parameters) -> torch.Tensor:
    return torch.nn.utils.parameters_to_vector(parameters).detach()


def _same_point(a: tuple, b: tuple) -> bool:
    """Equal parameter values and the very same element starts."""
    return torch.equal(a[0], b[0]) and len(a[1]) == len(b[1]) and all(x is y for x, y in zip(a[1], b[1]))


def _same_state(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def _copy_state(module: torch.nn.Module) -> dict:
    return {name: value.detach().clone() for name, value in module.state_dict().items()}


def _variance(values: np.ndarray) -> float:
    variance = float(np.var(values))
    return variance if variance > 0 else max(float(np.mean(np.asarray(values) ** 2)), 1.0)


# ------------------------------------------------------------------------------------------
# pre-training

# The pre-trainings' Adam fit of the ANN alone: samples per step, step size.
PRETRAINING_BATCH = 512
PRETRAINING_LEARNING_RATE = 3e-3


def neutral_pretraining(model: NeuralFMU, inputs: np.ndarray, channels: np.ndarray, iterations: int) -> float:
    """NIPT: fit the ANN part so that it leaves the hybrid unchanged on the reference's inputs.
    Returns the final relative mean squared error."""
    topology = model.topology
    x = torch.from_numpy(np.ascontiguousarray(inputs))
    target = topology.neutral_target(torch.from_numpy(np.ascontiguousarray(channels)))
    return _fit_ann(topology, x, target, iterations)


def _fit_ann(topology, x: torch.Tensor, target: torch.Tensor, iterations: int) -> float:
    """Least-squares fit of topology.correction(x) to target, relative to the target's spread."""
    scale = target.var(dim=0, unbiased=False).clamp_min(1e-12) if len(target) > 1 else torch.ones(target.shape[1])
    optimizer = torch.optim.Adam(topology.ann.parameters(), lr=PRETRAINING_LEARNING_RATE)
    generator = torch.Generator().manual_seed(0)
    n = x.shape[0]
    for _ in range(iterations):
        index = torch.randint(0, n, (min(PRETRAINING_BATCH, n),), generator=generator)
        loss = ((topology.correction(x[index]) - target[index]) ** 2 / scale).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    optimizer.zero_grad(set_to_none=True)
    with torch.no_grad():
        return float(((topology.correction(x) - target) ** 2 / scale).mean())


def collocation_pretraining(trainer: Trainer) -> float:
    """CCPT (see the module docstring): the collocation target fitted with Adam on minibatches;
    returns the final relative fit error, nan if no channel has a measured state."""
    from .warm_start import collocation_targets
    samples = collocation_targets(trainer)
    if samples is None:
        return math.nan
    x, target = samples
    return _fit_ann(trainer.model.topology, x, target, trainer.settings.ccpt_iterations)
