"""Which variables the ANN reads: those that predict the missing term on data it was not fitted to.

A fit on the samples alone rewards any variable that tells the samples apart, a cumulative one
(an energy, a position, an angle: a proxy for time) best of all; an ANN reading it extrapolates
on every other run. A flexible smoother also finds something in pure noise. So the inputs are
chosen by cross-validated error with a test against noise, cheaply, without training a NeuralFMU
per choice:

1. The missing derivative term along the measured trajectory (collocation): the FMU is run with its
   measured states forced to the data, and at each data stamp

       missing = slope of the measured state  -  the FMU's derivative of it (averaged alike)

   both by the same local linear fit (on the measured state and on the integral of the model's
   derivative), so that the sensor noise and the events' steps are smoothed the same way. The
   integrators the data do not measure follow the plain run. Where the data measure an output the model
   equals to the derivative (a power and der(energy)), missing = that output - the model's, no slope.
2. Samples: those of the training and validation windows where the model's derivative is settled
   (its swing within the slope window at most the SETTLED_QUANTILE of all swings): at steps and
   events the local fits straddle two regimes, and the estimate there follows the step, not the
   effect.
3. Candidates: the FMU's variables along that run; dropped are constant ones, the channel's own
   derivative and variables equal to it, variables whose validation values leave the range seen in
   training (decided from the data, not the names), and copies of a variable kept before (a
   torque proportional to a current).
4. Forward selection scored by a k-nearest-neighbour smoother of the missing term under FOLDS-fold
   cross-validation with contiguous folds (blocks of time, the validation window the last one): a
   cumulative variable's held-out values lie beyond those it was fitted on, so it extrapolates as
   it would on new data. A variable is admitted only if it lowers the cross-validated error by
   MIN_GAIN and a paired test over time blocks of BLOCK_SECONDS (the log-ratio of each block's
   error with and without it; t >= MIN_T) says the gain is no chance. A product of two variables
   needs both: the smoother sees the pair, and a pair is admitted at once when it passes both tests
   against the best single variable (a proxy of the two would be taken first otherwise). At most
   MAX_INPUTS.
5. A closed loop: a controller that holds the channel's state compensates the missing term, so the
   channel's own estimate shows nothing (its integrator, unmeasured, holds the difference). The
   compensation shows in the measured derivatives the controller drives (an energy): the inputs
   are then those that predict the missing term there (`inputs_through_loop`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..diagnose.trace import KIND_ORDER
from ..simulation.results import equal_along
from .evaluate import Scoring, simulate_over

# Share of held-out samples outside the training range (widened by RANGE_MARGIN of its width) above
# which a variable is not offered to the ANN.
OUT_OF_RANGE_SHARE = 0.1
RANGE_MARGIN = 0.05
# Two variables whose training values correlate beyond this are one input.
DUPLICATE_CORRELATION = 0.999
# A further input must lower the cross-validated error by this share of the error so far ...
MIN_GAIN = 0.1
# ... and the paired test over time blocks must give at least this t (log-ratio of block errors).
MIN_T = 3.0
# Seconds per block of the paired test: longer than the slope window and the sensors' noise
# correlation, so that the blocks' errors are about independent.
BLOCK_SECONDS = 1.2
# Contiguous cross-validation folds; neighbours of the smoother (standardised inputs).
FOLDS = 5
NEIGHBOURS = 20
# The ANN reads at most this many inputs.
MAX_INPUTS = 3
# Samples kept: those whose model-derivative swing is at most this quantile of all swings.
SETTLED_QUANTILE = 0.7
# Cross-validated errors within this share of the best are a tie: the preferred variable wins
# (measured signals first, then by kind), since such a difference is no evidence.
TIE = 0.05
# Seconds of data per local fit of the measured state's slope.
SLOPE_WINDOW = 0.6
# Pairs are tried among this many variables of lowest cross-validated error alone.
PAIR_POOL = 8


@dataclass
class InputChoice:
    channel: str
    inputs: list[str]
    validation_error: float             # cross-validated MSE of the smoother with the chosen inputs
    baseline_error: float               # cross-validated MSE of the mean (no input)
    steps: list[dict] = field(default_factory=list)   # per admitted input: variable, error, t
    rejected: dict = field(default_factory=dict)      # best variable not admitted: error, t
    out_of_range: dict = field(default_factory=dict)  # variable -> held-out share outside
    duplicates: dict = field(default_factory=dict)    # dropped variable -> the one kept

    @property
    def explained(self) -> float:
        """Share of the cross-validated variance of the missing term the inputs predict."""
        return 1.0 - self.validation_error / self.baseline_error if self.baseline_error > 0 else 0.0

    def to_dict(self) -> dict:
        return {"channel": self.channel, "inputs": self.inputs, "validation_error": self.validation_error,
                "baseline_error": self.baseline_error, "explained": self.explained, "steps": self.steps,
                "rejected": self.rejected, "out_of_range": self.out_of_range, "duplicates": self.duplicates}


@dataclass
class MissingTerm:
    """The missing term of each channel and the candidate variables at the data's stamps."""
    time: np.ndarray
    missing: dict[str, np.ndarray]      # channel -> estimate at each stamp
    variables: dict[str, np.ndarray]    # candidate -> value at each stamp
    kinds: dict[str, str]
    measured: set = field(default_factory=set)      # candidates that are measured signals
    aliases: dict = field(default_factory=dict)     # channel -> variables equal to it in the model


# -- step 1: the missing term along the measured trajectory ---------------------------------------

class MissingTermRun:
    """The missing terms of one run `data` for any channels asked for (`estimate`), from the FMU
    forced to the measured states over the whole run. The sensors' lag (the data's `sensor_lag`) is
    undone on the forced states and applied to the FMU's variables, so that both sides are compared
    as the sensors saw them. The simulations are done once: the plain run (by the engine) records
    the unmeasured integrators, which the forced run follows, and every measured channel that reads
    an unmeasured state; the forced run records the candidates and every measured channel. A second
    set of channels (the loop's measured derivatives) then costs no simulation."""

    def __init__(self, model_fmu, info, data, start_values: dict, candidates: list[str], step: float,
                 solver: str = "euler"):
        self.model_fmu, self.info, self.data, self.start_values = model_fmu, info, data, start_values
        self.candidates, self.step, self.solver = list(candidates), step, solver
        self.measured_channels = _measured_channels(info, data)
        self.lag = float(data.sensor_lag or 0.0)
        self._forced = None       # (grid, {name: values}, {name: values seen through the lag})
        self._plain = None        # (time, {name: values}) of the plain run

    def estimate(self, channels: list[str]) -> MissingTerm | None:
        """The missing term of each of `channels`; None when no channel's state is measured."""
        from scipy.integrate import cumulative_trapezoid

        from ..diagnose.trace import variable_kind
        from ..neural.collocation import local_slope
        from ..simulation.results import sample_settled
        info, data = self.info, self.data
        states = [v.name for v in info.states]
        derivatives = [v.name for v in info.derivatives]
        channel_states = {c: states[derivatives.index(c)] for c in channels}
        channels = [c for c in channels if channel_states[c] in data.signals]
        if not channels:
            return None
        candidates = list(dict.fromkeys([*self.candidates, *channels]))
        grid, values, seen = self._forced_run(candidates)
        seen = dict(seen)
        # A channel whose derivative reads an unmeasured state (a controller's integrator) is compared
        # with the plain model's run instead: its unmeasured states are right as long as the effect
        # does not feed back into them (the forced run takes its integrators from it too), and its
        # measured ones are the closed loop's own.
        unforced = [c for c in channels if not _reads_measured_only(info, c, data)]
        if unforced:
            time, plain = self._plain_run()
            seen.update({c: sample_settled(time, self._seen(time, plain[c]), grid) for c in unforced})
        at = data.time
        sampled = {n: np.interp(at, grid, values[n]) for n in candidates}
        aliases = {c: equal_to(sampled, c) for c in channels}
        missing = {}
        for c in channels:
            measured_alias = next((n for n in aliases[c] if n in data.signals), None)
            if measured_alias is not None:
                # The derivative is measured itself (a power the model equals to der(energy)): the
                # difference needs no slope, whose noise on the DC drive's energy (1.8 W rms) was a
                # third of the loss it estimates; the power's is 0.7 W.
                missing[c] = data.signals[measured_alias] - np.interp(at, grid, seen[c])
                continue
            # The same local fit on the measured state and on the integral of the model's derivative:
            # one linear operator on both, so that steps at events cancel instead of leaving spikes.
            slope, valid = local_slope(at, data.signals[channel_states[c]], at, SLOPE_WINDOW)
            model_integral = np.interp(at, grid, cumulative_trapezoid(seen[c], grid, initial=0.0))
            model_slope, _ = local_slope(at, model_integral, at, SLOPE_WINDOW)
            missing[c] = np.where(valid, slope - model_slope, np.nan)
        sampled = {n: np.interp(at, grid, seen[n]) for n in candidates}
        return MissingTerm(at, missing, sampled, {n: variable_kind(info, n) for n in candidates},
                           {n for n in candidates if n in data.signals}, aliases)

    def _seen(self, grid: np.ndarray, values: np.ndarray) -> np.ndarray:
        from ..data import first_order_lag
        return first_order_lag(grid, values, self.lag) if self.lag > 0 else values

    def _integrators(self) -> list[str]:
        """The unmeasured integrators: the forced run takes them from the plain run (as
        collocation.with_plain_unmeasured would, by a plain run of its own)."""
        from ..neural.collocation import unmeasured_integrators
        return unmeasured_integrators(self.info, self.data.signals)

    def _forced_run(self, names: list[str]):
        if self._forced is None or any(n not in self._forced[1] for n in names):
            data, states = self.data, [v.name for v in self.info.states]
            forced = {s: _undo_lag(data.time, data.signals[s], self.lag) for s in states if s in data.signals}
            integrators = self._integrators() if forced else []
            plain = self._plain_run() if integrators else None
            recorded = list(dict.fromkeys([*names, *self.measured_channels]))
            grid, values = _forced_run(self.model_fmu, self.info, data, self.start_values, forced, recorded,
                                       self.step, self.solver, integrators, plain)
            self._forced = grid, values, {n: self._seen(grid, v) for n, v in values.items()}
        return self._forced

    def _plain_run(self):
        if self._plain is None:
            compared = [c for c in self.measured_channels if not _reads_measured_only(self.info, c, self.data)]
            recorded = list(dict.fromkeys([*self._integrators(), *compared]))
            self._plain = _plain_run(self.model_fmu, self.data, self.start_values, recorded, self.step, self.solver)
        return self._plain


def _plain_run(model_fmu, data, start_values: dict, names: list[str], step: float, solver: str):
    """(time, {name: values}) of the plain FMU over the run, by the engine (the batch solver's
    steps, a sixth of its time: nothing is forced), recorded every step and on both sides of events."""
    result = simulate_over(model_fmu, data, start_values, names, Scoring(solver, step))
    return result.time, {n: np.asarray(result[n], dtype=float) for n in names}


def _reads_measured_only(info, channel: str, data) -> bool:
    """Whether the FMU's derivative `channel` depends only on measured states and FMU inputs
    (its ModelStructure dependencies; none declared: on everything)."""
    dependencies = info.dependencies.get(channel)
    if dependencies is None:
        return False
    known = set(data.signals) | set(getattr(data, "inputs", {}) or {})
    return all(name in known for name in dependencies)


def _undo_lag(time: np.ndarray, measured: np.ndarray, lag: float) -> np.ndarray:
    """The sensed quantity before a first-order sensor lag: y + lag * dy/dt (dy/dt from local fits)."""
    if lag <= 0:
        return measured
    from ..neural.collocation import local_slope
    slope, valid = local_slope(time, measured, time, SLOPE_WINDOW)
    return measured + lag * np.where(valid, slope, 0.0)


def _forced_run(model_fmu, info, data, start_values, forced: dict, names, step, solver, integrators=(), plain=None):
    """(grid, {name: values}) of the plain FMU with the states in `forced` (name -> values at the
    data's stamps) set after every step, so that its controllers react to the measured behaviour,
    and the `integrators` to the run `plain` ((time, {name: values})); none forced: the plain run."""
    from ..neural import NeuralFMU
    from ..neural.collocation import forced_run
    from ..neural.topology import TopologyConfig
    from ..simulation.results import sample_settled
    states = [v.name for v in info.states]

    def values_at(t):
        t = np.atleast_1d(np.asarray(t, dtype=float))
        return np.stack([np.interp(t, data.time, forced[s]) for s in forced]
                        + [sample_settled(plain[0], plain[1][s], t) for s in integrators], axis=1)

    config = TopologyConfig(channels=[info.derivatives[0].name], inputs=[states[0]], kind="residual")
    model = NeuralFMU(model_fmu, config, start_values)
    try:
        run = forced_run(model, data, step, solver, [*forced, *integrators], values_at, list(names),
                         data.input_signals(info))
        return data.start + np.asarray(run.times), {n: np.asarray(run.numpy(n)[:, 0], dtype=float) for n in names}
    finally:
        model.close()


# -- steps 2 to 4: samples, candidates and the forward selection -----------------------------------

def choose_inputs(term: MissingTerm, channel: str, train: np.ndarray, validation: np.ndarray) -> InputChoice:
    """Inputs for the ANN at `channel`; train and validation: boolean masks over term.time.
    The cross-validation runs over the settled samples of both, in time order."""
    target = term.missing[channel]
    usable = np.isfinite(target)
    train, validation = train & usable, validation & usable
    out_of_range = {n: share for n in term.variables
                    if (share := outside_share(term.variables[n][train], term.variables[n][validation])) > OUT_OF_RANGE_SHARE}
    exclude = {channel, *term.aliases.get(channel, ())}
    candidates = [n for n in term.variables if n not in exclude and n not in out_of_range
                  and np.ptp(term.variables[n][train]) > 0]
    candidates.sort(key=lambda n: (n not in term.measured, KIND_ORDER.get(term.kinds.get(n), 5)))
    kept, duplicates = distinct_variables(term.variables, candidates, train)
    samples = (train | validation) & settled_samples(term.time, term.variables.get(channel), train | validation)
    selection = forward_selection({n: term.variables[n][samples] for n in kept}, target[samples], term.time[samples],
                                  term.measured)
    return InputChoice(channel, selection.inputs, selection.error, selection.baseline, selection.steps,
                       selection.rejected, out_of_range, duplicates)


def settled_samples(time: np.ndarray, derivative: np.ndarray | None, among: np.ndarray) -> np.ndarray:
    """Mask of the samples whose model derivative swings (max - min within the slope window) by at
    most the SETTLED_QUANTILE of the swings among `among`; all when the derivative is not known."""
    if derivative is None:
        return np.ones(time.size, dtype=bool)
    lo = np.searchsorted(time, time - 0.5 * SLOPE_WINDOW, side="left")
    hi = np.searchsorted(time, time + 0.5 * SLOPE_WINDOW, side="right")
    swing = np.array([np.ptp(derivative[i:j]) for i, j in zip(lo, hi)])
    return swing <= np.quantile(swing[among], SETTLED_QUANTILE) if among.any() else np.zeros(time.size, dtype=bool)


@dataclass
class Selection:
    inputs: list[str]
    error: float                # cross-validated MSE with the inputs
    baseline: float             # cross-validated MSE of the mean
    steps: list[dict]
    rejected: dict


def forward_selection(variables: dict[str, np.ndarray], target: np.ndarray, time: np.ndarray,
                      measured: frozenset | set = frozenset()) -> Selection:
    """Admit, one at a time, the variable whose addition lowers the cross-validated error most
    among those that pass both tests (MIN_GAIN and the paired test); samples in time order, the
    variables in order of preference (ties go to the earlier one). A pair is admitted at once when
    it beats the best single addition by both tests too (see better_pair); `measured`: the variables
    the data measure."""
    names = list(variables)
    standardised = {n: (v - np.mean(v)) / (np.std(v) or 1.0) for n, v in variables.items()}
    blocks = time_blocks(time)
    current = cross_validated_squared_errors(None, target)
    baseline = error = float(np.mean(current)) if target.size else 0.0
    chosen, steps, rejected = [], [], {}

    def trial(added):
        squared = cross_validated_squared_errors(np.column_stack([standardised[n] for n in [*chosen, *added]]), target)
        return float(np.mean(squared)), paired_t(squared, current, blocks), squared

    while len(chosen) < MAX_INPUTS and target.size >= 2 * FOLDS:
        trials = {(n,): trial([n]) for n in names if n not in chosen}
        passing = {n: t for n, t in trials.items() if t[0] <= (1.0 - MIN_GAIN) * error and t[1] >= MIN_T}
        if len(chosen) + 2 <= MAX_INPUTS:
            pair = better_pair(trials, passing, trial, blocks, error, measured)
            if pair is not None:
                passing = {pair[0]: pair[1]}
        if not passing:
            if trials:
                best = min(trials, key=lambda n: trials[n][0])
                rejected = {"variable": best[0], "cv_error": trials[best][0], "t": trials[best][1]}
            break
        lowest = min(t[0] for t in passing.values())
        best = next(n for n in passing if passing[n][0] <= (1.0 + TIE) * lowest)   # dicts keep the preference order
        if len(best) == 2:      # a pair: its first variable's step is that variable's addition alone
            steps.append({"variable": best[0], "cv_error": trials[best[:1]][0], "t": trials[best[:1]][1]})
        error, t, current = passing[best]
        chosen.extend(best)
        steps.append({"variable": best[-1], "cv_error": error, "t": t})
    return Selection(chosen, error, baseline, steps, rejected)


def better_pair(trials: dict, passing: dict, trial, blocks: np.ndarray, error: float, measured=frozenset()):
    """(pair, its trial) of two further variables that together beat the best single addition (or,
    none passing, the error so far) by MIN_GAIN with t >= MIN_T against it, or None. An effect of
    two variables together (a product) is not found one variable at a time when a third variable,
    a proxy of both (a controller's integrator, which holds the voltage the load and speed ask
    for), predicts more than either alone: taken first, it leaves the pair no room. The pairs are
    those among the PAIR_POOL variables of lowest error alone, in order of preference; a pair the data
    measure wins over one the model computes whenever it passes (on the DC drive's loss a copper loss,
    R(T) i^2, with the speed fitted the smoother closer than the current with it: the square folds
    the current's sign, which |speed * current| ignores, onto half the samples' space)."""
    pool = sorted(trials, key=lambda n: trials[n][0])[:PAIR_POOL]
    pool = [n for n in trials if n in pool]                 # back in the order of preference
    if len(pool) < 2:
        return None
    # against the best single addition that passes; none passing: against the error so far, as a single
    reference = min(passing.values(), key=lambda t: t[0]) if passing else None
    pairs = {}
    for i, first in enumerate(pool):
        for second in pool[i + 1:]:
            pair_error, t, squared = trial([*first, *second])
            if reference is not None:
                t = paired_t(squared, reference[2], blocks)
            if pair_error <= (1.0 - MIN_GAIN) * (reference[0] if reference else error) and t >= MIN_T:
                pairs[first + second] = (pair_error, t, squared)
    if not pairs:
        return None
    pairs = {p: v for p, v in pairs.items() if set(p) <= set(measured)} or pairs
    lowest = min(v[0] for v in pairs.values())
    best = next(p for p in pairs if pairs[p][0] <= (1.0 + TIE) * lowest)
    return best, pairs[best]


def cross_validated_squared_errors(x: np.ndarray | None, target: np.ndarray) -> np.ndarray:
    """Squared error at each sample of a NEIGHBOURS-nearest-neighbour mean of the target fitted on
    the other folds (FOLDS contiguous folds); x None: the other folds' mean."""
    from scipy.spatial import cKDTree
    fold = contiguous_folds(target.size)
    predicted = np.empty(target.size)
    for f in range(FOLDS):
        held_out, fitted = fold == f, fold != f
        if not held_out.any():
            continue
        if x is None:
            predicted[held_out] = np.mean(target[fitted])
            continue
        k = min(NEIGHBOURS, int(fitted.sum()))
        _, index = cKDTree(x[fitted]).query(x[held_out], k=k)
        predicted[held_out] = target[fitted][np.asarray(index).reshape(-1, k)].mean(axis=1)
    return (target - predicted) ** 2


def contiguous_folds(count: int) -> np.ndarray:
    """Fold index of each of `count` samples in time order: FOLDS runs of consecutive samples."""
    return (np.arange(count) * FOLDS) // max(count, 1)


def time_blocks(time: np.ndarray) -> np.ndarray:
    """Block index of each sample: a new block every BLOCK_SECONDS and where time runs backwards
    (the next of several runs joined)."""
    blocks = np.zeros(time.size, dtype=int)
    block, start = 0, time[0] if time.size else 0.0
    for i in range(1, time.size):
        if time[i] < time[i - 1] or time[i] - start >= BLOCK_SECONDS:
            block, start = block + 1, time[i]
        blocks[i] = block
    return blocks


def paired_t(new: np.ndarray, old: np.ndarray, blocks: np.ndarray) -> float:
    """t of the mean log-ratio old/new of the blocks' mean squared errors (positive: new is lower)."""
    counts = np.bincount(blocks)
    used = counts > 0
    tiny = 1e-300
    ratio = (np.log(np.bincount(blocks, old)[used] / counts[used] + tiny)
             - np.log(np.bincount(blocks, new)[used] / counts[used] + tiny))
    if ratio.size < 3:
        return 0.0
    spread = float(np.std(ratio, ddof=1))
    if spread == 0.0:
        return float("inf") if np.mean(ratio) > 0 else 0.0
    return float(np.mean(ratio) / (spread / np.sqrt(ratio.size)))


def equal_to(variables: dict, channel: str) -> list[str]:
    """Variables equal to the channel's derivative along the run (a power whose integral is an
    energy state): an ANN reading them would read its own output."""
    if channel not in variables:
        return []
    return [n for n in equal_along(variables, variables[channel]) if n != channel]


def outside_share(train_values: np.ndarray, held_out: np.ndarray) -> float:
    """Share of held-out values outside the training range widened by RANGE_MARGIN of its width."""
    lo, hi = float(np.min(train_values)), float(np.max(train_values))
    margin = RANGE_MARGIN * (hi - lo)
    return float(np.mean((held_out < lo - margin) | (held_out > hi + margin))) if held_out.size else 0.0


def distinct_variables(variables: dict, ordered: list[str], mask: np.ndarray) -> tuple[list[str], dict]:
    """`ordered` without variables that are (anti)proportional to an earlier one on the training samples."""
    kept, duplicates = [], {}
    for name in ordered:
        x = variables[name][mask]
        twin = next((k for k in kept if abs(np.corrcoef(x, variables[k][mask])[0, 1]) > DUPLICATE_CORRELATION), None)
        if twin is None:
            kept.append(name)
        else:
            duplicates[name] = twin
    return kept, duplicates


# -- the workflow's choice: channels and inputs -----------------------------------------------------

# A channel the diagnosis found about as good as its best one is corrected too when the inputs
# predict this share of its estimated missing term under cross-validation.
EXTRA_CHANNEL_EXPLAINED = 0.5


@dataclass
class AnnChoice:
    channels: list[str]
    inputs: list[str]
    per_channel: list[InputChoice]
    # The measured channel whose estimate chose the inputs when the loop hides the channel's own
    # (see inputs_through_loop); None: each channel's own estimate chose them.
    through: InputChoice | None = None

    @property
    def channel_inputs(self) -> list[list[str]]:
        """Per channel the inputs chosen for it: its correction reads those alone (an input another
        channel needs is not evidence for this one)."""
        if self.through is not None:
            return [list(self.inputs)]
        return [list(c.inputs) for c in self.per_channel]

    def to_dict(self) -> dict:
        chosen = {"channels": self.channels, "inputs": self.inputs, "rule": "forward selection by the "
                  "cross-validated error (contiguous folds) of a nearest-neighbour smoother of the estimated missing "
                  f"term; an input must lower it by {MIN_GAIN:.0%} with t >= {MIN_T:g} over {BLOCK_SECONDS:g} s blocks",
                  "per_channel": [c.to_dict() for c in self.per_channel]}
        if self.through is not None:
            chosen["through"] = {"rule": "the channel's own estimate admitted nothing (a controller compensates the "
                                 "term along the measured run); the inputs are those that predict the missing term "
                                 f"of the measured derivative {self.through.channel}, where the compensation shows, "
                                 "without the channel itself", **self.through.to_dict()}
        return chosen


def choose_ann(model_fmu, info, train_parts, validation_parts, channel: str, further: list[str],
               step: float, solver: str) -> AnnChoice | None:
    """Channels and inputs of the ANN: `channel` (the diagnosis' best) and those of `further`
    whose missing term the chosen inputs predict on held-out data. Parts: objects with `data`,
    `start_values` and `window` (the workflow's roles). None when the channel's state is not
    measured or no variable predicts its missing term: the caller falls back to the diagnosis."""
    from ..diagnose.trace import candidate_variables
    runs, estimators = [], []
    for part in [*train_parts[:1], *validation_parts]:     # each run once, its simulations shared by both estimates
        if all(part.data is not run.data for run in runs):
            runs.append(part)
            estimators.append(MissingTermRun(model_fmu, info, part.data, part.start_values,
                                             candidate_variables(info), step, solver))

    def estimated(channels):
        terms = [estimator.estimate(channels) for estimator in estimators]
        if any(t is None or channel not in t.missing for t in terms):
            return None, None, None
        train = np.concatenate([_in_windows(t, r.data, train_parts[:1]) for t, r in zip(terms, runs)])
        validation = np.concatenate([_in_windows(t, r.data, validation_parts) for t, r in zip(terms, runs)])
        return _joined(terms), train, validation

    term, train, validation = estimated([channel, *further])
    if term is None:
        return None
    first = choose_inputs(term, channel, train, validation)
    if not first.inputs:
        others = [c for c in _measured_channels(info, train_parts[0].data) if c != channel]
        if not others:
            return None
        term, train, validation = estimated(list(dict.fromkeys([channel, *further, *others])))
        through = inputs_through_loop(term, channel, [c for c in dict.fromkeys([*further, *others]) if c != channel],
                                      train, validation)
        if through is None:
            return None
        inputs = [n for n in through.inputs if n not in {channel, *term.aliases.get(channel, ())}]
        return AnnChoice([channel], inputs, [first], through)
    chosen = [first]
    for extra in further:
        if extra in term.missing:
            choice = choose_inputs(term, extra, train, validation)
            if choice.inputs and choice.explained >= EXTRA_CHANNEL_EXPLAINED:
                chosen.append(choice)
    inputs = list(dict.fromkeys(n for c in chosen for n in c.inputs))
    return AnnChoice([c.channel for c in chosen], inputs, chosen)


def inputs_through_loop(term: MissingTerm, channel: str, others: list[str], train: np.ndarray,
                        validation: np.ndarray) -> InputChoice | None:
    """The choice on another measured derivative for a channel whose own estimate admitted nothing.

    A controller that holds the channel's state compensates its missing term: along the measured
    run the model, its own controller holding the same state, shows no missing term there, and the
    controller's integrator, which would tell, is not measured. The compensation moves into the
    derivatives the controller drives (an energy, a current), where the plain model falls short of
    the data. The variables that predict that shortfall on held-out data are those the missing
    term is a function of. Of `others` (in order) the first whose inputs, the channel itself and
    its aliases left out, predict at least EXTRA_CHANNEL_EXPLAINED of its estimate; None if none does."""
    own = {channel, *term.aliases.get(channel, ())}
    for other in others:
        if other not in term.missing:
            continue
        choice = choose_inputs(term, other, train, validation)
        if choice.explained >= EXTRA_CHANNEL_EXPLAINED and any(n not in own for n in choice.inputs):
            return choice
    return None


def _measured_channels(info, data) -> list[str]:
    """The FMU's derivatives whose states the data measure."""
    return [d.name for s, d in zip(info.states, info.derivatives) if s.name in data.signals]


def _in_windows(term: MissingTerm, data, parts) -> np.ndarray:
    """Mask over term.time: the samples inside the windows of the parts of the run `data`."""
    mask = np.zeros(term.time.size, dtype=bool)
    for part in parts:
        if part.data is data:
            mask |= (term.time >= part.window[0]) & (term.time <= part.window[1])
    return mask


def _joined(terms: list[MissingTerm]) -> MissingTerm:
    """One MissingTerm of several runs, one after the other (the smoother ignores time). Each run's
    stamps are shifted to follow the run before it by more than a slope window and a test block, so
    that the time stays increasing (runs may each start at 0) and no window spans two runs."""
    if len(terms) == 1:
        return terms[0]
    first = terms[0]
    channels = [c for c in first.missing if all(c in t.missing for t in terms)]
    times, end = [], None
    for t in terms:
        shift = 0.0 if end is None else end + SLOPE_WINDOW + BLOCK_SECONDS - float(t.time[0])
        times.append(t.time + shift)
        end = float(times[-1][-1])
    return MissingTerm(np.concatenate(times),
                       {c: np.concatenate([t.missing[c] for t in terms]) for c in channels},
                       {n: np.concatenate([t.variables[n] for t in terms]) for n in first.variables},
                       first.kinds, set.union(*(t.measured for t in terms)), first.aliases)
