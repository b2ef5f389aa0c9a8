"""The diagnosis stage: how far is the declared model from the data, is that more than noise,
and where in the model does the missing effect act?

    from fmubuilder.diagnose import diagnose
    d = diagnose("vldm.fmu", "data.csv", plots_dir="plots")
    d.significant, d.channel, d.inputs, d.fitted_term, print(d.report())

1. The declared model is simulated over the data's time span with the data's start values
   (the sidecar's, the caller's, and a measured state's first samples when they contradict
   the model's start value), filtered like the sensors and sampled at the data's stamps.
2. Per signal: MSE, RMS, max |error|, final error, the noise level and its own test; one
   joint test of all signals (significance.py, robust to coloured and shared noise) decides
   whether there is a significant effect.
3. Only then the effect is traced (trace.py): channel = state derivative, inputs = variables
   the missing term depends on, and a fitted term when a compact expression explains it.
   The tracing covers at most the first TRACE_SAMPLES samples (``trace_window``); its work is
   counted (a fixed list of trials, each abandoned beyond SLOW_TRIAL_FACTOR times the plain
   run's work), and ``time_budget`` only caps the wall time (``cut_short`` says when it did).
"""
from __future__ import annotations

import math
import time as wallclock
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..errors import FmuBuilderError
from ..fmi.archive import read_model_info
from . import significance
from ..data import START_SAMPLES, MeasuredData, load_data
from .runs import ModelRun, ModelRunner, form_text, rms
from .trace import MAX_CHANNELS, SECOND_CHANNEL_RATIO, TracedTerm, Tracer, candidate_variables

TERM_MIN_EXPLAINED = 0.8       # a fitted term is offered when it removes this share of the excess chi-square
AMBIGUOUS = 1.1                # another channel whose best trial leaves less than 1.1 times the
                               # unexplained variance of the best one explains the data about as well
START_TOLERANCE = 4.0          # standard errors between a measured start and the model's
TRACE_SAMPLES = 1000           # the tracing's trials cover at most this many leading samples (100 s at 10 Hz)


@dataclass
class SignalErrors:
    signal: str
    mse: float
    rms: float
    max_abs: float
    final: float               # measured - model at the last sample
    noise: float               # noise level of the measured value (per sample)
    noise_dof: float           # degrees of freedom of the noise's variance estimate
    noise_from_spread: bool    # the noise level is capped by the data's spread column
    chi2_per_dof: float
    p_value: float
    significant: bool
    corrected_rms: float | None = None   # with the fitted term added


@dataclass
class Candidate:
    channel: str               # e.g. 'der(speed)'
    inputs: list[str]          # the variable (empty for a generic shape)
    form: str                  # e.g. 'speed*|speed|' (of speed - its start value)
    score: float               # explained variance, every signal weighted alike (decides the channel)
    shape_score: float         # explained variance, signals weighted by precision (ranks the inputs)
    coefficient: float         # least-squares coefficient of the form
    basis: str                 # the form as a term (base_term.py): basis of (variable - center)
    center: float
    equivalent: list[str] = field(default_factory=list)   # forms giving the same response


@dataclass
class Diagnosis:
    model: str
    data: str
    significant: bool
    p_value: float
    channel: str | None
    inputs: list[str]
    ambiguous_channels: list[str]      # channels that explain the data about as well
    candidates: list[Candidate]
    channel_scores: dict[str, float]
    errors: list[SignalErrors]
    fitted_term: dict | None
    start_values: dict
    start_values_from_data: dict
    window: tuple[float, float]        # data span
    trace_window: tuple[float, float] | None
    failed_trials: list[str] = field(default_factory=list)   # trial terms the model could not run
    cut_short: str | None = None       # set when the wall-time cap stopped the tracing early
    simulations: int = 0
    wall_time: dict = field(default_factory=dict)
    plots: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)

    def report(self) -> str:
        from .report import format_report
        return format_report(self)


def diagnose(model_fmu, data_csv, start_values: dict | None = None, plots_dir=None, *,
             time_budget: float | None = None, trace_always: bool = False) -> Diagnosis:
    """Compare the declared model with measured data and trace a significant difference.

    start_values: {name: value} for the model (added to those recorded with the data);
    plots_dir: folder for PNG plots (created); time_budget: an upper cap on the seconds the
    tracing may take (None: no cap); it never changes the numbers unless it cuts the tracing
    short, which ``cut_short`` then reports; trace_always: trace even when the residual is not
    significant.
    """
    started = wallclock.perf_counter()
    model_fmu = Path(model_fmu)
    info = read_model_info(model_fmu)
    # data_csv: a path, or data already loaded (e.g. the part of a run a workflow fits on)
    if isinstance(data_csv, MeasuredData):
        data, data_csv = data_csv, data_csv.source
    else:   # fewer than 8 samples cannot tell an effect from noise
        data_csv = Path(data_csv)
        data = load_data(data_csv, info, min_samples=8)
    start, stop = float(data.time[0]), float(data.time[-1])
    given = {**data.start_values, **(start_values or {})}
    variables = candidate_variables(info)
    runner = _runner(model_fmu, given, data, start, stop, variables)
    try:
        nominal = runner.simulate()
        _check_finite(nominal, model_fmu)
        from_data = start_values_from_data(info, data, given, nominal)
        if from_data:
            runner.start_values.update(from_data)
            nominal = runner.simulate()
            _check_finite(nominal, model_fmu)
        used = dict(runner.start_values)
        runner.output_aliases = derivative_aliases(info, nominal, data.names)
        errors, tests, joint = signal_errors(data, nominal)
        p_value, significant = joint.p_value, joint.significant
        wall = {"nominal": nominal.wall_time}
        diagnosis = Diagnosis(
            model=str(model_fmu), data=str(data_csv), significant=significant, p_value=p_value, channel=None,
            inputs=[], ambiguous_channels=[], candidates=[], channel_scores={}, errors=errors, fitted_term=None,
            start_values=used, start_values_from_data=from_data, window=(start, stop), trace_window=None)
        fitted_run = None
        if significant or trace_always:
            trace_started = wallclock.perf_counter()
            fitted_term = _trace(diagnosis, info, data, runner, nominal, tests, variables, time_budget)
            wall["trace"] = wallclock.perf_counter() - trace_started
            if fitted_term is not None:
                fitted_run = runner.simulate(fitted_term.terms, trajectories=False)
                _judge_term(diagnosis, data, nominal, fitted_run)
        diagnosis.simulations = runner.runs
        if plots_dir is not None:
            from .plots import write_plots
            plot_started = wallclock.perf_counter()
            diagnosis.plots = [str(p) for p in write_plots(Path(plots_dir), diagnosis, data, nominal, fitted_run,
                                                           info=info)]
            wall["plots"] = wallclock.perf_counter() - plot_started
    finally:
        runner.close()
    wall["simulation_mean"] = runner.total_wall_time / max(runner.runs, 1)
    wall["total"] = wallclock.perf_counter() - started
    diagnosis.wall_time = wall
    return diagnosis


# ---------------------------------------------------------------------------------------
# Steps


def _runner(model_fmu, start_values, data: MeasuredData, start, stop, variables) -> ModelRunner:
    return ModelRunner(model_fmu, start_values=start_values, data_time=data.time, start=start, stop=stop,
                       measured=data.names, recorded=variables, sensor_lag=data.sensor_lag,
                       fine_step=data.fine_step, inputs=data.inputs)


def _check_finite(run: ModelRun, model_fmu) -> None:
    for name, values in run.predicted.items():
        if not np.all(np.isfinite(values)):
            raise FmuBuilderError(
                f"simulating {model_fmu} over the data's time span gives non-finite values of '{name}'; "
                "check the start values (--start) against the data")


def start_values_from_data(info, data: MeasuredData, given: dict, nominal: ModelRun) -> dict:
    """Start values of measured states whose first samples contradict the model's run.

    The offset is the intercept of a line through the residual of the first few samples (few,
    because the state may soon change its course); a fast state that starts right but moves
    within the first sample interval leaves no offset. The offset moves the start value only
    when it exceeds START_TOLERANCE standard errors (from the residual's noise level), so that
    data recorded from the model's own start are not shifted by their noise."""
    found = {}
    states = {v.name: v for v in info.states}
    k = START_SAMPLES      # the same few samples as a simulation started at a measured time
    t = data.time[:k] - data.time[0]
    design = np.column_stack([np.ones(k), t / float(t[-1])])
    # Standard error of the intercept per unit noise: sqrt of (X^T X)^-1 [0, 0].
    unit_error = math.sqrt(float(np.linalg.inv(design.T @ design)[0, 0]))
    for name, values in data.signals.items():
        var = states.get(name)
        if var is None or name in given or var.start is None:
            continue
        residual = values - nominal.predicted[name]
        offset = float(np.linalg.lstsq(design, residual[:k], rcond=None)[0][0])
        fit = significance.fit_noise(residual, None, data.std.get(name), data.runs)
        # Correlated noise moves the first samples together: their intercept is as uncertain
        # as a mean of k samples, at most sqrt(k) times the white-noise case.
        noise = min(fit.long_run, math.sqrt(k) * fit.marginal)
        tolerance = START_TOLERANCE * noise * unit_error + significance.NUMERICAL_FLOOR * float(np.ptp(values))
        if abs(offset) > tolerance:
            found[name] = float(var.start) + offset
    return found


def derivative_aliases(info, nominal: ModelRun, measured: list[str]) -> dict[str, list[int]]:
    """Measured outputs that are a state derivative (e.g. a power whose integral is an energy
    state): a term added to that derivative must show in the output as well."""
    aliases = {}
    state_names = {v.name for v in info.states}
    for name in measured:
        if name in state_names:
            continue
        y = nominal.trajectories[name]
        for c, der in enumerate(info.derivatives):
            d = nominal.trajectories.get(der.name)
            if d is not None and np.max(np.abs(y - d)) <= 1e-9 * max(float(np.max(np.abs(y))), 1e-300):
                aliases.setdefault(name, []).append(c)
    return aliases


def signal_errors(data: MeasuredData, nominal: ModelRun):
    """Per-signal errors and tests, and the joint test of all signals."""
    errors, tests = [], []
    for name, measured in data.signals.items():
        model = nominal.predicted[name]
        residual = measured - model
        test = significance.signal_test(residual, model, data.std.get(name), data.runs)
        tests.append(test)
        errors.append(SignalErrors(
            signal=name, mse=float(np.mean(residual ** 2)), rms=rms(residual),
            max_abs=float(np.max(np.abs(residual))), final=float(residual[-1]), noise=test.noise,
            noise_dof=test.noise_dof, noise_from_spread=name in data.std,
            chi2_per_dof=test.chi2 / test.dof, p_value=test.p_value, significant=test.significant))
    return errors, tests, _joint_test(data, nominal)


def _joint_test(data: MeasuredData, run: ModelRun) -> significance.JointTest:
    names = data.names
    return significance.joint_test([data.signals[s] - run.predicted[s] for s in names],
                                   [run.predicted[s] for s in names], [data.std.get(s) for s in names], data.runs)


def _trace(diagnosis: Diagnosis, info, data: MeasuredData, runner: ModelRunner, nominal: ModelRun,
           tests, variables, time_budget: float | None) -> TracedTerm | None:
    """Trace the effect over the data's first TRACE_SAMPLES samples; a time budget only caps
    the wall time."""
    noise = {e.signal: math.hypot(t.noise, t.floor) for e, t in zip(diagnosis.errors, tests)}
    deadline = math.inf
    if time_budget is not None and math.isfinite(time_budget):
        deadline = wallclock.perf_counter() + time_budget
    trace_runner, trace_nominal = runner, nominal
    if data.time.size > TRACE_SAMPLES:
        start = diagnosis.window[0]
        trace_runner = _runner(runner.fmu.path, runner.start_values, data, start,
                               float(data.time[TRACE_SAMPLES - 1]), variables)
        trace_runner.output_aliases = runner.output_aliases
        trace_nominal = trace_runner.simulate()
    diagnosis.trace_window = (trace_runner.start, trace_runner.stop)
    try:
        return _trace_window(diagnosis, info, data, trace_runner, trace_nominal, noise, variables, deadline)
    finally:
        if trace_runner is not runner:
            runner.runs += trace_runner.runs
            runner.total_wall_time += trace_runner.total_wall_time
            trace_runner.close()
        if wallclock.perf_counter() > deadline:
            diagnosis.cut_short = (f"the time budget of {time_budget:g} s ran out while tracing: trials after it "
                                   "were skipped and the tracing may be incomplete; give a larger budget")


def _trace_window(diagnosis, info, data, runner, nominal, noise, variables, deadline) -> TracedTerm | None:
    in_window = (data.time >= runner.start) & (data.time <= runner.stop)
    measured = {name: values[in_window] for name, values in data.signals.items()}
    tracer = Tracer(runner, nominal, measured, noise)
    tracer.deadline = deadline
    if not tracer.rr > 0:
        return None     # the model meets the data exactly: nothing to trace
    channels = tracer.screen_channels()
    channel_name = {c: info.derivatives[c].name for c in range(info.n_states)}
    diagnosis.channel_scores = {channel_name[s.channel]: s.score for s in channels}
    ranked = sorted((s for s in channels if s.observable and s.score > 0), key=lambda s: -s.score)
    kept = [s for s in ranked[:MAX_CHANNELS] if s.score >= SECOND_CHANNEL_RATIO * ranked[0].score]
    forms = tracer.candidate_forms([v for v in variables if v in nominal.trajectories])
    trials_by_channel = {s.channel: tracer.rank_inputs(s, forms) for s in kept}
    trials_by_channel = {c: trials for c, trials in trials_by_channel.items() if trials}
    diagnosis.failed_trials = tracer.failed
    if not trials_by_channel:
        return None
    # The channel: whose best trial explains most of how every signal moved. Its variables
    # come ranked by how precisely they reproduce the residual's shape.
    best_score = {c: max(t.score for t in trials) for c, trials in trials_by_channel.items()}
    order = sorted(best_score, key=lambda c: -best_score[c])
    best = order[0]
    diagnosis.channel = channel_name[best]
    diagnosis.inputs = list(dict.fromkeys(t.variable for t in trials_by_channel[best]))
    diagnosis.ambiguous_channels = [channel_name[c] for c in order[1:]
                                    if 1.0 - best_score[c] < AMBIGUOUS * (1.0 - best_score[best])]
    diagnosis.candidates = [candidate_of(info, t) for c in order for t in trials_by_channel[c]]
    fitted = tracer.fit_term(trials_by_channel[best])
    if fitted is None:
        return None
    diagnosis.fitted_term = _fitted_dict(info, fitted)
    return fitted


def _judge_term(diagnosis: Diagnosis, data: MeasuredData, nominal: ModelRun, fitted_run: ModelRun) -> None:
    """Errors with the fitted term over the whole data span, and whether it is offered: it must
    remove TERM_MIN_EXPLAINED of the residual's excess over noise (block chi-square minus its
    degrees of freedom, summed over the signals). Before and after are measured against one noise
    estimate per signal, the corrected residual's, which holds less of the effect than the plain one:
    with two estimates the plain residual's effect, taken partly for noise, would shrink its own excess."""
    before = after = 0.0
    for e in diagnosis.errors:
        name, spread = e.signal, data.std.get(e.signal)
        model = fitted_run.predicted[name]
        residual = data.signals[name] - model
        e.corrected_rms = rms(residual)
        fit = significance.fit_noise(residual, model, spread, data.runs)
        was = significance.joint_test([data.signals[name] - nominal.predicted[name]], [model], [spread], data.runs,
                                      fits=[fit])
        now = significance.joint_test([residual], [model], [spread], data.runs, fits=[fit])
        before += max(0.0, was.chi2 - was.dof)
        after += max(0.0, now.chi2 - now.dof)
    removed = 1.0 - after / before if before > 0 else 0.0
    term = diagnosis.fitted_term
    term["explained_excess"] = float(removed)
    term["corrected_p_value"] = float(_joint_test(data, fitted_run).p_value)
    term["offered"] = bool(removed >= TERM_MIN_EXPLAINED)


def candidate_of(info, trial) -> Candidate:
    """A trial of the trace as a ranked candidate of the diagnosis."""
    return Candidate(channel=info.derivatives[trial.channel].name, inputs=[trial.variable],
                     form=form_text(trial.variable, trial.basis, trial.center), score=trial.score,
                     shape_score=trial.shape_score, coefficient=trial.coefficient, basis=trial.basis,
                     center=float(trial.center), equivalent=list(trial.equivalent))


def _fitted_dict(info, fitted: TracedTerm) -> dict:
    channel = info.derivatives[fitted.channel].name
    expression = " + ".join(t.expression() for t in fitted.terms).replace("+ -", "- ")
    return {
        "channel": channel,
        "expression": f"{channel} += {expression}",
        "terms": [{"variable": t.variable, "basis": t.basis, "center": t.center, "coefficient": t.coefficient,
                   "form": t.form()} for t in fitted.terms],
        "explained_variance_linear": fitted.explained_variance,
        "explained_variance": fitted.verified_explained_variance,
        "explained_excess": None,       # set by _judge_term
        "corrected_p_value": None,
        "offered": False,
    }

