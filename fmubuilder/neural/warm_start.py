"""Warm start of a NeuralFMU from the data, without the ODE solver.

Closed-loop-aware collocation: the FMU runs along the measured trajectory (its measured states
forced to the data after every step, so its own controllers, relays and integrators react to the
measured behaviour as the real ones did), the derivative of each measured state is estimated from
the data by local linear fits (a smoothing differentiator, see collocation.local_slope), and the
difference, measured derivative minus the FMU's own, estimates the missing term as a function of
the ANN's inputs along that run. The ANN is fitted to it full-batch with L-BFGS (a few hundred
evaluations of a tiny network on some 10^4 samples: a second or two), then the training through
the solver fine-tunes it from there instead of from zero. The same difference along the plain
model's own run, nothing forced, is a second estimate (ESTIMATES); the simulated training loss
chooses between the fits.

The integral target (`warm_start_target="integral"`, the weak form) compares increments instead of
slopes: over windows [a, b] of the data, x(b) - x(a) minus the FMU derivative's integral along the
forced run is what the ANN's integral (trapezoid rule on the run's grid, in torch) has to give.
No window is left out: the state is continuous where its derivative jumps, and a window across a
sign change is matched by the ANN's mean over it, not assigned to one point's inputs.

From the kept fit (or from zero where none lowered the loss, or where the one kept fitted its
estimate's noise: the estimate did not see the effect), the last layer is then fitted through the
simulation itself (Levenberg-Marquardt, see last_layer.py; from the unfitted ANN a second time from
a fresh Jacobian), which sees what a controller does with the effect and what the estimate's noise
left in the fit.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from .collocation import collocation_samples, integral_samples, unmeasured_integrators

# The bounded fit (fit_full_batch): grid points over the inputs' range, and the share of the
# target's samples at either end left out of its range (single outliers of the estimate).
RANGE_POINTS = 1024
RANGE_QUANTILE = 0.001
# The fit's L2 penalty on the ANN's weights and biases, against the target's variance as 1
# (benchmarks/bench_representation.py --collocation: on the DC drive's Stribeck and Coulomb
# estimates the whole-run temperature error of the warm-started hybrid fell about 10-fold with it).
WEIGHT_DECAY = 1e-4
# The decays the warm start fits with, each from the same start; the simulated training loss picks
# one. The strong one keeps a fit to a noisy estimate from turning on the noise; the weak one lets a
# steep effect be steep (a Coulomb friction's sign over 1 rad/s of the DC drive's speeds from -120 to
# 200 rad/s: its warm-started hybrid's training loss 22.8 with the strong decay, 2.87 with the weak;
# docs/MEASUREMENTS.md, "The warm start's weight decay chosen by the simulation").
WEIGHT_DECAYS = (WEIGHT_DECAY, 1e-6)
# The estimates fitted, each with every decay: "forced", along the run with the measured states
# forced (the module docstring), and "plain", the measured derivative minus the plain model's along
# its own run, nothing forced. Forcing a noisy measured state can set a controller off: on the VLDM's
# extra loss (10 % of the motor's power on der(energy)) the speed forced to its local lines (0.011 m/s
# rms off) moved the driver's der(speed) 0.42 m/s^2 rms off the truth's (rms 0.48), and the forced
# estimate was 7.47 kW rms off a loss of rms 772 W; the plain run's was 248 W off
# (benchmarks/bench_loss_floor.py). Where the effect moves the trajectory the plain one is off
# instead; the simulated training loss decides.
ESTIMATES = ("forced", "plain")
# After the fits the ANN's last layer is fitted through the simulation (last_layer.py, from the
# parameters kept so far: a simulation per unknown for the Jacobian, then this many
# Levenberg-Marquardt trials), kept if the training loss falls. Where a controller compensates the
# effect along the measured run (the VLDM's driver holds the speed on the cycle: the speed's slope
# shows nothing, the drive power all of it) the collocation estimate explains 8 % of its own
# variance and the fits to it raise the loss 16-fold; the simulation sees the closed loop's own
# response to each hidden unit. Where a fit is kept, the estimate's noise leaves a bias the
# simulation sees and the fit does not (docs/MEASUREMENTS.md, "The warm start's two estimates").
THROUGH_SIMULATION_TRIALS = 4
# Where the kept fit leaves more than this share of the training loss before it, the last layer is
# also fitted through the simulation from the unfitted ANN, and the start with the lower loss kept:
# a fit that hardly lowers the loss has fitted the estimate's noise, and its hidden units can serve
# the simulation's regression worse than the initial ones (the demo's NeuralFMU: the plain run's
# estimate of der(speed), which the driver's loop hides, lowered the loss 0.6 %; through the
# simulation from that fit 2.32, from the unfitted ANN 1.60).
UNFITTED_TOO_ABOVE = 0.5
# Where such a fit also leaves more than this share of its own estimate's variance unexplained
# (fit_error), it has fitted the estimate's noise, not a faint effect: the last layer is then fitted
# from the unfitted ANN alone, with UNFITTED_TRIALS trials instead of both starts' 2 x 4. The demo's
# NeuralFMU (its kept fit explains 0.2 % of the plain run's estimate), the search's loss over the
# whole training run: from the unfitted ANN 2.04 after 4 trials, 1.046 after 12, 1.0453 after 52;
# from the fit 2.06 after 4, 1.36 after 16, 1.21 after 40; validation score 49.2 with both starts'
# 4 trials, 18.4 with 12 (the demo), 16 and 60 (docs/MEASUREMENTS.md, "The warm start from the
# unfitted ANN alone"). A faint estimate of the right shape (a fifth of the effect) explains itself
# and keeps both starts: its fit's start wins there (tests/neural/test_warm_start.py), as on the
# DC drive's two effects' ANN on the term (fit error 0.03).
FITTED_NOISE_ABOVE = 0.5
UNFITTED_TRIALS = 12
# That search from the unfitted ANN is then run once more from where it ended, its Jacobian taken
# afresh, with this many trials: Broyden's updates of the first Jacobian stall on these nearly
# dependent hidden units. The demo's NeuralFMU: the whole-run loss where the first search ended 1.0458,
# after the second 1.0111 (a third: 1.0111), the validation score after the warm start 19.6 -> 12.7,
# of the trained NeuralFMU 18.4 -> 12.1, its test score 3.08 -> 2.65 (docs/MEASUREMENTS.md, "The
# search from the unfitted ANN taken up again"; measured with the layer's entries as the unknowns,
# the training loss 1.0285 -> 1.0182; along its data's directions, last_layer.py, 1.3375 -> 1.0172).
RESTART_TRIALS = 12
# Simulations without gradient in one _loss_from_own_starts: the capture of the starts and the loss.
LOSS_SIMULATIONS = 2


def collocation_targets(trainer, force: bool = True):
    """(raw ANN inputs [N, n_in], target of the ANN part [N, C]) along the measured trajectory (with
    force=False along the plain run), or None when no channel's state is measured. Channels without
    a measured state keep the neutral target (the ANN leaves them unchanged)."""
    model, settings = trainer.model, trainer.settings
    samples = collocation_samples(model, trainer.data, trainer.step, settings.solver, settings.ccpt_window,
                                  trainer.inputs, settings.sensor_lag or 0.0, force)
    if samples is None:
        return None
    inputs, fmu_channels, measured, mask = samples
    target = _ann_part(model.topology, measured, fmu_channels, mask)
    # Samples with no valid estimate (a window across a step, see collocation.smooth_windows) are
    # left out rather than pulled to the neutral target.
    rows = torch.from_numpy(mask.any(axis=1))
    return torch.from_numpy(np.ascontiguousarray(inputs))[rows], target[rows]


def integral_targets(trainer, force: bool = True):
    """The weak form of collocation_targets: (raw ANN inputs on the forced run's grid [N, n_in],
    target of the ANN part's mean over each window [W, C], WindowMeans mapping the ANN part on the
    grid to its window means), or None when no channel's state is measured."""
    model, settings = trainer.model, trainer.settings
    samples = integral_samples(model, trainer.data, trainer.step, settings.solver, trainer.inputs,
                               settings.sensor_lag or 0.0, span=settings.integral_window, force=force)
    if samples is None:
        return None
    inputs, fmu_channels, means, measured, mask = samples
    with torch.no_grad():
        fmu_means = means(torch.from_numpy(fmu_channels)).numpy()
    target = _ann_part(model.topology, measured, fmu_means, mask,
                       neutral=means(model.topology.neutral_target(torch.from_numpy(fmu_channels))))
    rows = mask.any(axis=1)
    return torch.from_numpy(np.ascontiguousarray(inputs)), target[torch.from_numpy(rows)], means.subset(rows)


def _ann_part(topology, measured: np.ndarray, fmu_channels: np.ndarray, mask: np.ndarray, neutral=None):
    """What the ANN part has to give where the channel's state is measured, the neutral target
    elsewhere: gate_ann * r + gate_fmu * der_fmu = measured -> r = (measured - gate_fmu der_fmu) / gate_ann."""
    with torch.no_grad():
        if topology.config.kind == "gates" and bool((topology.gate_ann == 0).any()):
            topology.gate_ann.fill_(1.0)
        gate_ann, gate_fmu = topology.gate_ann.detach(), topology.gate_fmu.detach()
    fmu = torch.from_numpy(fmu_channels)
    target = (torch.from_numpy(measured) - gate_fmu * fmu) / gate_ann
    if neutral is None:
        neutral = topology.neutral_target(fmu)
    return torch.where(torch.from_numpy(mask), target, neutral.detach())


def fit_full_batch(topology, x: torch.Tensor, target: torch.Tensor, iterations: int, bounded: bool = True,
                   weight_decay: float = WEIGHT_DECAY, average=None) -> float:
    """Least-squares fit of topology.correction(x) to target with L-BFGS over all samples at once
    (the ANN's weights only; the pre-/post-processing stays). Returns the final mean squared error
    relative to the target's variance; a line search that made it worse leaves the start.

    With `bounded`, the fit also pays for the ANN leaving the target's range on a grid spread
    uniformly over the inputs' range (`range_penalty`): an unconstrained fit swings far out inside
    the gaps the samples leave. `weight_decay` times the sum of the ANN's squared weights and biases
    is added: a steep fit to the estimate's noise puts wrong turns between the samples (both in
    numbers: docs/MEASUREMENTS.md, "Warm starts, optimizers and an ANN on the fitted term").

    With `average` (the integral target, collocation.WindowMeans) the correction is evaluated at
    every x and its window means are what meets the target, one row per window; the range bound
    stays on the pointwise correction."""
    average = average or (lambda values: values)
    scale = _target_scale(target)
    parameters = list(topology.ann.parameters())
    penalty = range_penalty(x, target, scale) if bounded else (lambda _: 0.0)
    optimizer = torch.optim.LBFGS(parameters, lr=1.0, max_iter=iterations, max_eval=int(iterations * 1.25) + 1,
                                  history_size=20, tolerance_grad=1e-10, tolerance_change=1e-14,
                                  line_search_fn="strong_wolfe")

    def objective():
        decay = weight_decay * sum((p ** 2).sum() for p in parameters) if weight_decay else 0.0
        return (((average(topology.correction(x)) - target) ** 2) / scale).mean() + penalty(topology) + decay

    def closure():
        optimizer.zero_grad()
        loss = objective()
        loss.backward()
        return loss

    best = _copy(parameters)
    with torch.no_grad():
        start_loss = float(objective())
    optimizer.step(closure)
    optimizer.zero_grad(set_to_none=True)
    with torch.no_grad():
        loss = float(objective())
        if not math.isfinite(loss) or loss > start_loss:     # a diverged line search: keep the start
            _restore(parameters, best)
        return fit_error(topology, x, target, average)


def fit_error(topology, x: torch.Tensor, target: torch.Tensor, average=None) -> float:
    """Mean squared error of the correction (window means with `average`) against the target,
    relative to the target's variance per channel."""
    with torch.no_grad():
        correction = topology.correction(x)
        correction = average(correction) if average is not None else correction
        return float((((correction - target) ** 2) / _target_scale(target)).mean())


def _target_scale(target: torch.Tensor) -> torch.Tensor:
    return target.var(dim=0, unbiased=False).clamp_min(1e-12) if len(target) > 1 else torch.ones(target.shape[1])


def range_penalty(x: torch.Tensor, target: torch.Tensor, scale: torch.Tensor, points: int = RANGE_POINTS):
    """topology -> the mean square (relative to `scale`) by which the correction leaves the
    target's [RANGE_QUANTILE, 1 - RANGE_QUANTILE] range per channel, on `points` inputs spread
    uniformly over the box of the samples' inputs (a fixed low-discrepancy set: the fit stays
    deterministic). Zero for a correction that stays within the range the samples show."""
    low_in, high_in = x.min(dim=0).values, x.max(dim=0).values
    grid = torch.quasirandom.SobolEngine(x.shape[1], scramble=False).draw(points, dtype=x.dtype)
    grid = low_in + grid * (high_in - low_in)
    low, high = (torch.quantile(target, q, dim=0) for q in (RANGE_QUANTILE, 1.0 - RANGE_QUANTILE))

    def penalty(topology):
        out = topology.correction(grid)
        beyond = torch.relu(out - high) + torch.relu(low - out)
        return ((beyond ** 2) / scale).mean()
    return penalty


def warm_start(trainer) -> dict:
    """Fit the ANN to each of ESTIMATES of the missing term (see the module docstring) with each of
    WEIGHT_DECAYS, and keep the fit with the lowest training loss (simulated over all elements, each
    from the start the hybrid reaches) if it is lower than without a fit: where the forced
    controllers react to sensor noise and lag more than to the effect, the forced estimate is wrong,
    and where the effect moves the trajectory, the plain one. With a sub-network per channel, each
    channel then tries the other fits of its own block, one channel at a time (two effects may ask
    for different fits). Then the last layer is fitted through the simulation (from the unfitted ANN
    too where the kept fit hardly lowered the loss: UNFITTED_TOO_ABOVE; from it alone where that fit
    also explains little of its estimate: FITTED_NOISE_ABOVE). Returns what it did:
    samples (windows with the integral target) of the kept estimate, the target, relative fit error
    to its own estimate (nan without a measured channel state, or with channels from different
    estimates), the training loss before, after the fits and after all, the estimate and decay kept
    per channel, every trial, the fit through the simulation (None if not possible), whether
    anything was kept."""
    integral = trainer.settings.warm_start_target == "integral"
    targets = integral_targets if integral else collocation_targets
    first = targets(trainer)
    if first is None:
        return {"samples": 0, "fit_error": math.nan, "kept": False}
    topology = trainer.model.topology
    search = _Search(trainer)
    samples = {}
    for estimate in ESTIMATES:
        samples[estimate] = first if estimate == "forced" else targets(trainer, force=False)
        x, target, average = samples[estimate] if integral else (*samples[estimate], None)
        search.unfitted.apply(topology)
        scale_output_to_effect(topology, target)
        for decay in WEIGHT_DECAYS:
            search.unfitted.apply(topology, post_scale=False)
            error = fit_full_batch(topology, x, target, trainer.settings.warm_start_iterations, weight_decay=decay,
                                   average=average)
            search.try_fit((estimate, decay), error)
    search.splice_channels()
    search.keep_best()
    if search.fitted_noise():
        return _summary(trainer, search, samples, _unfitted_instead(trainer, search))
    through = _through_simulation(trainer, search.best["loss"])
    if through is not None and search.hardly_lowered():
        through = _unfitted_too(trainer, search, through)
    return _summary(trainer, search, samples, through)


def _summary(trainer, search, samples: dict, through: dict | None) -> dict:
    """warm_start's report (see there)."""
    best = search.best
    # simulations without gradient: a run per estimate (and the plain run the forced one's unmeasured
    # states follow), a capture and a loss before and per trial, and one more each when the last
    # trial is not the one kept
    unmeasured = bool(unmeasured_integrators(trainer.model.info, trainer.data.signals))
    simulations = (len(ESTIMATES) + LOSS_SIMULATIONS * (1 + len(search.trials) + search.restored)
                   + unmeasured)
    loss_after = best["loss"]
    if through is not None:
        simulations += through["simulations"]
        loss_after = through["loss"] if through["kept"] else loss_after
    kept = best["fits"] is not None and (through is None or through.get("start") != "unfitted")
    chosen = best if kept else search.trials[0]
    estimate = chosen["estimates"][0] if len(set(chosen["estimates"])) == 1 else None
    return {"samples": int(samples[estimate or "forced"][1].shape[0]), "target": trainer.settings.warm_start_target,
            "fit_error": chosen["fit_error"], "loss_before": search.loss_before, "loss_fits": best["loss"],
            "loss_after": loss_after,
            "kept": kept or bool(through and through["kept"]), "estimate": best["estimates"] if kept else None,
            "weight_decay": best["decays"] if kept else None,
            "trials": [{k: v for k, v in t.items() if k != "fits"} for t in search.trials],
            "through_simulation": through, "simulations": simulations}


def _unfitted_too(trainer, search, through: dict) -> dict:
    """The last layer through the simulation from the unfitted ANN as well (UNFITTED_TOO_ABOVE), the
    start with the lower training loss kept; its report, with the start ("fit" or "unfitted"), both
    starts' losses after it and both paths' simulations."""
    other, from_fit = _search_from_unfitted(trainer, search, THROUGH_SIMULATION_TRIALS)
    simulations = through["simulations"] + other["simulations"]
    losses = {"loss_from_fit": through["loss"], "loss_from_unfitted": other["loss"]}
    if other["loss"] < through["loss"]:
        return {**other, **losses, "kept": True, "start": "unfitted", "simulations": simulations}
    _back_to_fit(trainer, from_fit)
    return {**through, **losses, "start": "fit", "simulations": simulations + LOSS_SIMULATIONS}


def _unfitted_instead(trainer, search) -> dict:
    """The last layer through the simulation from the unfitted ANN alone, with UNFITTED_TRIALS
    trials and RESTART_TRIALS more from a fresh Jacobian (the kept fit has fitted its estimate's
    noise: FITTED_NOISE_ABOVE); the fit back in place where that does not lower the training loss
    below the fit's. Its report as _unfitted_too's, without a loss from the fit."""
    done, from_fit = _search_from_unfitted(trainer, search, UNFITTED_TRIALS)
    done = _searched_again(trainer, done)
    done["loss_from_unfitted"] = done["loss"]
    if done["loss"] < search.best["loss"]:
        return {**done, "kept": True, "start": "unfitted"}
    _back_to_fit(trainer, from_fit)
    return {**done, "loss": search.best["loss"], "kept": False, "start": "fit",
            "simulations": done["simulations"] + LOSS_SIMULATIONS}


def _searched_again(trainer, done: dict) -> dict:
    """The last layer's search once more from where `done` (a search's report) left it, a Jacobian
    taken afresh and RESTART_TRIALS trials; `done` with the lower loss, both searches' simulations and
    the second's report ("again": its loss before and after, whether kept)."""
    again = _through_simulation(trainer, done["loss"], RESTART_TRIALS)
    if again is None:
        return done
    summary = {"loss_before": done["loss"], "loss": again["loss"], "kept": again["kept"],
               "simulations": again["simulations"]}
    return {**done, "loss": again["loss"] if again["kept"] else done["loss"], "kept": done["kept"] or again["kept"],
            "simulations": done["simulations"] + again["simulations"], "again": summary}


def _search_from_unfitted(trainer, search, trials: int) -> tuple[dict, _Fit]:
    """(_through_simulation's report from the unfitted ANN with `trials` trials, its simulations
    counting the capture of the element starts; the fit's parameters it replaced)."""
    topology = trainer.model.topology
    from_fit = _Fit.of(topology)
    search.unfitted_start().apply(topology)
    # its output scale acts on the unfitted last layer (zero): the hybrid is the one before the
    # fits, whose loss the search measured; only the element starts need capturing again
    trainer._capture_starts(plain=topology.is_neutral())
    loss = search.loss_before
    done = _through_simulation(trainer, loss, trials) or {"simulations": 0, "loss": loss, "kept": False}
    return {**done, "simulations": done["simulations"] + 1}, from_fit


def _back_to_fit(trainer, from_fit: _Fit) -> None:
    """The fit's parameters back in place, the element starts captured again with them."""
    from_fit.apply(trainer.model.topology)
    _loss_from_own_starts(trainer)


class _Search:
    """The warm start's fits, each simulated: the training loss of every trial (a fit, or channels
    spliced from several) and the best one."""

    def __init__(self, trainer):
        self.trainer, self.topology = trainer, trainer.model.topology
        self.unfitted = _Fit.of(self.topology)
        self.loss_before = _loss_from_own_starts(trainer)
        self.fitted: dict[tuple[str, float], _Fit] = {}
        self.trials: list[dict] = []
        self.best = {"loss": self.loss_before, "fits": None, "fit_error": math.nan}
        self.restored = False

    def try_fit(self, key: tuple[str, float], error: float) -> None:
        """The topology's current parameters, the fit to estimate key[0] with decay key[1], simulated."""
        self.fitted[key] = _Fit.of(self.topology)
        self._simulate([key] * len(self.topology.config.channels), error)

    def splice_channels(self) -> None:
        """With a sub-network per channel, each channel tries the other fits' blocks in turn."""
        owners = self.topology.row_channels()
        if owners is None or self.best["fits"] is None:
            return
        for channel in range(len(self.topology.config.channels)):
            for key in self.fitted:
                if key != self.best["fits"][channel]:
                    keys = [*self.best["fits"][:channel], key, *self.best["fits"][channel + 1:]]
                    _spliced(self.fitted, keys, owners).apply(self.topology)
                    self._simulate(keys, math.nan)

    def keep_best(self) -> None:
        """The best trial's parameters back in place, the element starts with them; nothing kept:
        the ANN at zero, its output scaled to the first estimate's effect."""
        if self.trials[-1] is self.best:
            return
        if self.best["fits"] is not None:
            _spliced(self.fitted, self.best["fits"], self.topology.row_channels()).apply(self.topology)
        else:
            self.unfitted_start().apply(self.topology)
        _loss_from_own_starts(self.trainer)
        self.restored = True

    def hardly_lowered(self) -> bool:
        """Whether a fit is kept that left more than UNFITTED_TOO_ABOVE of the loss before it."""
        return self.best["fits"] is not None and self.best["loss"] > UNFITTED_TOO_ABOVE * self.loss_before

    def fitted_noise(self) -> bool:
        """Whether the kept fit hardly lowered the loss and left more than FITTED_NOISE_ABOVE of its
        estimate's variance (channels spliced from several fits have no fit error: no)."""
        return self.hardly_lowered() and self.best["fit_error"] > FITTED_NOISE_ABOVE

    def unfitted_start(self) -> _Fit:
        """The ANN as before the fits, its output scaled to the first estimate's effect."""
        return _Fit(self.unfitted.parameters, self.fitted[ESTIMATES[0], WEIGHT_DECAYS[0]].post_scale)

    def _simulate(self, keys: list[tuple[str, float]], error: float) -> None:
        self.trials.append({"estimates": [k[0] for k in keys], "decays": [k[1] for k in keys], "fits": keys,
                            "fit_error": error, "loss": _loss_from_own_starts(self.trainer)})
        if self.trials[-1]["loss"] < self.best["loss"]:
            self.best = self.trials[-1]


def _through_simulation(trainer, loss: float, trials: int = THROUGH_SIMULATION_TRIALS) -> dict:
    """The last layer fitted through the simulation from the current parameters (their training
    loss `loss`; a Jacobian and `trials` trials, see THROUGH_SIMULATION_TRIALS), kept if the
    training loss falls, each step it keeps scored on the validation data (last_layer.py).
    Returns what it did."""
    from .last_layer import refine_last_layer
    topology = trainer.model.topology
    parameters = list(topology.ann.parameters())
    start = _copy(parameters)
    unknowns = int(topology.last_layer_free().sum()) + topology.ann[-1].bias.numel()
    refined = refine_last_layer(trainer, unknowns + 1 + trials,
                                "warm start: the ANN's last layer through the simulation", stage=(0, "warm start"))
    if refined is None:
        return None
    done = {"simulations": refined["simulations"], "loss": loss, "kept": False}
    if refined["kept"]:
        done["loss"] = _loss_from_own_starts(trainer)
        done["simulations"] += LOSS_SIMULATIONS
        done["kept"] = done["loss"] < loss
    if not done["kept"]:
        _restore(parameters, start)
        if refined["kept"]:
            _loss_from_own_starts(trainer)
            done["simulations"] += LOSS_SIMULATIONS
    return done


class _Fit:
    """One fit's ANN parameters and the output scale it was fitted with (scale_output_to_effect)."""

    def __init__(self, parameters: list[torch.Tensor], post_scale: torch.Tensor):
        self.parameters, self.post_scale = parameters, post_scale

    @classmethod
    def of(cls, topology) -> "_Fit":
        return cls(_copy(topology.ann.parameters()), topology.post_scale.detach().clone())

    def apply(self, topology, post_scale: bool = True) -> None:
        _restore(list(topology.ann.parameters()), self.parameters)
        if post_scale:
            with torch.no_grad():
                topology.post_scale.copy_(self.post_scale)


def _spliced(fitted: dict, keys: list, owners: list[torch.Tensor] | None) -> _Fit:
    """The fit with channel c's rows of the ANN and its output scale from fitted[keys[c]] (one key:
    that fit)."""
    if owners is None or len(set(keys)) == 1:
        return fitted[keys[0]]
    parameters = []
    for i, owner in enumerate(owners):
        rows = [fitted[keys[int(c)]].parameters[i][r] for r, c in enumerate(owner)]
        parameters.append(torch.stack(rows))
    post_scale = torch.stack([fitted[key].post_scale[c] for c, key in enumerate(keys)])
    return _Fit(parameters, post_scale)


def scale_output_to_effect(topology, target: torch.Tensor) -> None:
    """Residual topology: the ANN's output scaled to the root mean square of the estimated effect
    per channel instead of the channel derivative's spread (on the DC drive 10-40 times larger
    than a friction term), so that a step of the network's weights moves the correction by a share
    of the effect, not of the whole derivative. The last layer is still zero: the hybrid is
    unchanged by it."""
    if topology.config.kind != "residual" or len(target) < 2:
        return
    size = target.pow(2).mean(dim=0).sqrt()
    with torch.no_grad():
        current = topology.post_scale.detach().clone()
        topology.post_scale.copy_(torch.where(size > 0, torch.minimum(size, current), current))


def _loss_from_own_starts(trainer) -> float:
    """The training loss over all elements, their starts captured from the current hybrid."""
    trainer._capture_starts(plain=trainer.model.topology.is_neutral())
    residual = trainer.scaled_residuals()
    return float(residual @ residual)


def _copy(parameters) -> list[torch.Tensor]:
    return [p.detach().clone() for p in parameters]


def _restore(parameters, saved: list[torch.Tensor]) -> None:
    with torch.no_grad():
        for p, value in zip(parameters, saved):
            p.copy_(value)
