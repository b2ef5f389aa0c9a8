"""`fmubuilder hybridize`: diagnose, build the candidates, choose one on the validation data,
validate its round trip, score the test data once, report.

The data's roles and the candidates are the README's "Data and their roles in `hybridize`" and "The
candidates"; each number in the report comes from one role. The work is counted, not timed (the
README's demo paragraph); `time_budget` is an optional wall-clock cap on the training, and the
report says when it cut it short.
"""
from __future__ import annotations

import shutil
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..data import MeasuredData
from ..errors import FmuBuilderError
from ..files import copy_atomically, keep_for_the_user, refuse_existing, replace_folder, staging_folder
from ..fmi import read_model_info
from ..fmi.side_process import SideProcess, can_run_beside, cores
from ..progress import counted
from ..progress import set_enabled as set_progress_enabled
from .evaluate import Scoring, evaluate, read_data, relative_mse, signal_errors
from .recipe import VALIDATION_SHARE, held_out_windows

# The NeuralFMU training's work: loss evaluations, each a simulation of all training elements with
# its gradient (an Adam step costs one, an L-BFGS step its line search's, see neural.train.Trainer.fit).
DEFAULT_BUDGET = 10
# The NeuralFMU's derivative is searched, not only traced: every derivative the diagnosis cannot rule
# out (those whose change moves a measured signal, the traced one first) gets its network's warm
# start (fitted to the collocation estimate of the missing term, no gradient through the solver:
# SCREEN_BUDGET loss evaluations), scored on the validation data, and the one with the lowest score
# is trained with the full budget. At most SEARCH_CHANNELS derivatives: each costs a warm start.
SCREEN_BUDGET = 0
SEARCH_CHANNELS = 4
# Seconds of the test data replayed by the round-trip validation (fmpy Euler and CVode).
ROUNDTRIP_SPAN = 60.0
# ANN inputs when they cannot be chosen on held-out data (hybridize.inputs, which decides how many
# when it can): the leading traced variable.
MAX_ANN_INPUTS = 1
# The NeuralFMU's training recipe (optimizer, elements, loss scale, warm start, last layer, the
# noise floor rule): recipe.py, which `fmubuilder train --recipe hybridize` reads too.
# Seconds of the training data on which outputs equal to the corrected derivative are detected.
ALIAS_SPAN = 60.0


@dataclass
class Part:
    """The samples of one data set that play one role; the model is simulated over the whole run."""
    data: MeasuredData
    start_values: dict
    window: tuple[float, float]

    @property
    def file_name(self) -> str:
        return Path(self.data.path).name if self.data.path else self.data.source

    @property
    def label(self) -> str:
        whole = self.window == (self.data.start, self.data.stop)
        return self.file_name if whole else f"{self.file_name} [{self.window[0]:g}, {self.window[1]:g}] s"

    def samples(self) -> MeasuredData:
        return self.data.window(*self.window)


@dataclass
class Roles:
    train: list[Part]
    validation: list[Part]
    test: Part
    held_out_of_training: bool       # validation = the late share of each training run

    def describe(self) -> dict:
        parts = {role: [p.label for p in parts] for role, parts in
                 (("train", self.train), ("validation", self.validation), ("test", [self.test]))}
        parts["validation_from"] = (f"the last {VALIDATION_SHARE:.0%} of each training run, held out of the fit"
                                    if self.held_out_of_training else "a separate run")
        return parts


@dataclass
class Scores:
    """A model's errors per role (over all the role's samples) and its runs for the plots."""
    fmu: Path
    errors: dict = field(default_factory=dict)        # role -> signal -> {"mse", "max_abs", "final"}
    runs: dict = field(default_factory=dict)          # id(data) -> Evaluation over the whole run


@dataclass
class Candidate:
    name: str                      # "neural", "fitted term" or "calibrated <parameter>"
    description: str
    fmu: Path
    spec_dir: Path
    scores: Scores
    details: dict = field(default_factory=dict)


@dataclass
class HybridizeResult:
    report: dict
    report_dir: Path
    hybrid_fmu: Path | None


def hybridize(model_fmu, train_csv, test_csv, output_fmu, report_dir, *, validation_csv=None,
              train_start: dict | list | None = None, validation_start: dict | None = None,
              test_start: dict | None = None, budget: int = DEFAULT_BUDGET, seed: int = 0,
              time_budget: float | None = None, force: bool = False, allow_insignificant: bool = False,
              ann_on_term: bool = True, progress: bool = True, jobs: int | None = None) -> HybridizeResult:
    """train_csv: one data file or a list of them; train_start: start values for all of them, or a
    list with one dict per file (added to each file's sidecar). time_budget: optional wall-clock cap
    in seconds on the NeuralFMU's training (the work is `budget`, in loss evaluations). force: overwrite the outputs (the
    old ones stay until the new ones are complete); allow_insignificant: build the candidates even
    when the diagnosis finds no significant effect; ann_on_term: also train an ANN that starts from
    the fitted term and learns what it leaves, whenever a term is offered that leaves more than the
    noise (term_started.py, _at_noise_floor); jobs: processes for the candidates, 2 to train the
    NeuralFMU and calibrate beside the fitted term (the default with two or more cores), 1 for one
    after the other; the numbers are the same."""
    started = time.perf_counter()
    model_fmu, output_fmu, report_dir = Path(model_fmu), Path(output_fmu), Path(report_dir)
    _check_outputs(output_fmu, report_dir, force)
    if not isinstance(budget, int) or budget < 0:
        raise FmuBuilderError(f"the training budget must be a whole number of loss evaluations >= 0, got {budget}")
    if time_budget is not None and not time_budget > 0:
        raise FmuBuilderError(f"time budget {time_budget:g} s: give a positive number of seconds or none")
    if jobs is None:
        jobs = min(2, cores())
    elif not isinstance(jobs, int) or jobs < 1:
        raise FmuBuilderError(f"jobs must be a whole number of processes >= 1, got {jobs}")
    info = read_model_info(model_fmu)
    roles = _assign_roles(info, train_csv, train_start, validation_csv, validation_start, test_csv, test_start)
    work = Path(tempfile.mkdtemp(prefix="fmubuilder-hybridize-"))
    final_report_dir, report_dir = report_dir, staging_folder(report_dir)   # swapped in when complete
    try:
        say = print if progress else (lambda *a, **k: None)
        first = roles.train[0]
        say(f"[1/5] diagnosing {model_fmu.name} against {first.label} ...")
        from ..diagnose import diagnose
        diagnosis = diagnose(model_fmu, first.samples(), first.start_values, plots_dir=report_dir / "diagnosis",
                             trace_always=allow_insignificant)
        for part in (*roles.train, *roles.validation):     # the diagnosis' start values belong to its run
            if part.data is first.data:
                part.start_values = {**part.start_values, **diagnosis.start_values}
        say(f"      {_diagnosis_line(diagnosis)}")
        estimated = _estimate_noise(roles, diagnosis)
        if estimated:
            say(f"      noise estimated from the data (no spread column): {estimated}")
        # Every model, and the NeuralFMU's training, at an RK4 step whose error lies below the noise.
        scoring = Scoring.checked(model_fmu, first.samples(), first.start_values)
        say(f"      scoring: {scoring.describe()}")
        timings = {"diagnosis": time.perf_counter() - started}
        plain = score(Scores(model_fmu), roles, scoring, ("train", "validation"), "scoring the plain FMU")
        candidates: list[Candidate] = []
        training, not_trained, failed = None, {}, {}
        if diagnosis.significant or allow_insignificant:
            context = _Context(model_fmu, info, roles, scoring, work, say, budget, seed, time_budget, started, plain,
                               progress=progress, ann_on_term=ann_on_term, jobs=jobs)
            candidates_started = time.perf_counter()
            candidates = _build_candidates(context, diagnosis)
            training, not_trained, failed = context.training, context.not_trained, context.failed
            timings["candidates"] = time.perf_counter() - candidates_started
        selection = {**_select(candidates, plain, roles.validation), "not_trained": not_trained, "failed": failed}
        chosen = next((c for c in candidates if c.name == selection["chosen"]), None)
        # Everything is decided: now, and only now, the test data.
        say("      scoring every model on the test data (once, after the choice) ...")
        for name, model in (("the plain FMU", plain), *((f"the {c.name} hybrid", c.scores) for c in candidates)):
            score(model, roles, scoring, ("test",), f"test data: {name}")
        hybrid_path, roundtrip = None, None
        if chosen is not None:
            say(f"[4/5] validating the round trip of the {chosen.name} hybrid ...")
            roundtrip_started = time.perf_counter()
            roundtrip = _roundtrip(chosen, roles.test)
            timings["roundtrip"] = time.perf_counter() - roundtrip_started
            hybrid_path = output_fmu if roundtrip["passed"] else None     # what was scored, or nothing
        say("[5/5] writing the report ...")
        from .report import write_report
        report = write_report(report_dir, model_fmu=model_fmu, diagnosis=diagnosis, plain=plain,
                              candidates=candidates, chosen=chosen, selection=selection, roundtrip=roundtrip,
                              hybrid_fmu=hybrid_path, roles=roles, scoring=scoring, training=training,
                              seconds=time.perf_counter() - started, timings=timings)
        if hybrid_path is not None:     # published with its report, once both are complete
            _publish(chosen.fmu, output_fmu, force)
        replace_folder(report_dir, final_report_dir)
        if (chosen is not None and hybrid_path is None) or (failed and not candidates):
            keep_for_the_user(final_report_dir)     # the errors below point to it
        if chosen is not None and hybrid_path is None:
            raise FmuBuilderError(f"the chosen {chosen.name} hybrid failed its round trip, so nothing was written; "
                                  f"see its comparisons in the report: {final_report_dir / 'report.md'}")
        if failed and not candidates:
            raise FmuBuilderError(f"no candidate could be built: {_reasons(failed)}; the report: "
                                  f"{final_report_dir / 'report.md'}")
        return HybridizeResult(report, final_report_dir, hybrid_path)
    finally:
        shutil.rmtree(work, ignore_errors=True)
        shutil.rmtree(report_dir, ignore_errors=True)   # the staged report of a failed run


# -- roles of the data ----------------------------------------------------------------------------

def _assign_roles(info, train_csv, train_start, validation_csv, validation_start, test_csv, test_start) -> Roles:
    paths = [train_csv] if isinstance(train_csv, (str, Path)) else list(train_csv)
    if not paths:
        raise FmuBuilderError("no training data: give at least one --train DATA.csv")
    starts = train_start if isinstance(train_start, list) else [train_start] * len(paths)
    if len(starts) != len(paths):
        raise FmuBuilderError(f"{len(starts)} sets of training start values for {len(paths)} training files; "
                              "give one per file")
    train = [_whole_run(info, p, s) for p, s in zip(paths, starts)]
    test = _whole_run(info, test_csv, test_start)
    if validation_csv is not None:
        return Roles(train, [_whole_run(info, validation_csv, validation_start)], test, held_out_of_training=False)
    validation = []
    for part in train:
        part.window, held_out = held_out_windows(part.data)
        validation.append(Part(part.data, part.start_values, held_out))
    return Roles(train, validation, test, held_out_of_training=True)


def _whole_run(info, path, start_values: dict | None) -> Part:
    """All samples of a data file, its sidecar's start values overridden by `start_values`."""
    data = read_data(Path(path), info)
    return Part(data, {**data.start_values, **(start_values or {})}, (data.start, data.stop))


def _estimate_noise(roles: Roles, diagnosis) -> str:
    """Give every signal without a spread column the noise variance the diagnosis estimated from the
    training data's residual (the significance test's noise fit), in every role: the sensors are
    the same, and the scores measure each model against the noise. Returns the estimates as text."""
    estimates = {e.signal: e.noise ** 2 for e in diagnosis.errors if not e.noise_from_spread and e.noise > 0}
    for part in (*roles.train, *roles.validation, roles.test):
        part.data.noise_estimate.update({name: v for name, v in estimates.items() if name not in part.data.std})
    uncertainty = {e.signal: (2.0 / max(e.noise_dof, 1.0)) ** 0.5 for e in diagnosis.errors}
    return ", ".join(f"{name} σ = {v ** 0.5:.3g} (variance ±{uncertainty[name]:.0%})" for name, v in estimates.items())


# -- scoring ------------------------------------------------------------------------------------

def score(scores: Scores, roles: Roles, scoring: Scoring, which: tuple[str, ...], label: str = "scoring") -> Scores:
    """Errors of the model on the roles in `which`, over all of each role's samples; each run is
    simulated once (a training run gives both its fit part and its held-out tail)."""
    parts_of = {"train": roles.train, "validation": roles.validation, "test": [roles.test]}
    todo = {id(p.data): p for role in which for p in parts_of[role] if id(p.data) not in scores.runs}
    for key, part in counted(list(todo.items()), label, "run"):
        scores.runs[key] = evaluate(scores.fmu, part.data, part.start_values, scoring)
    for role in which:
        parts = parts_of[role]
        pieces = []
        for part in parts:
            run = scores.runs[id(part.data)]
            pieces.append((part.data.signals, run.predicted, (run.time >= part.window[0]) & (run.time <= part.window[1])))
        scores.errors[role] = {name: signal_errors(np.concatenate([m[name][k] for m, _, k in pieces]),
                                                   np.concatenate([p[name][k] for _, p, k in pieces]))
                               for name in parts[0].data.names}
    return scores


def _select(candidates: list[Candidate], plain: Scores, validation: list[Part] = ()) -> dict:
    """The candidate chosen on the validation data (choice.py; the rule: the README's "The candidates"),
    on the floors and margin of _validation_floors."""
    from ..score import validation_score
    from .choice import RULE, choose
    errors = plain.errors["validation"]
    floors, margin, _ = _validation_floors(plain, validation)
    scores = {c.name: validation_score(c.scores.errors["validation"], floors) for c in candidates}
    plain_score = validation_score(errors, floors)
    return {"on": "validation", "scores": scores, "chosen": choose(scores, plain_score, margin),
            "plain_score": plain_score, "margin": margin,
            "relative_to_plain": {c.name: relative_mse(errors, c.scores.errors["validation"]) for c in candidates},
            "rule": RULE.format(margin=margin, plain=plain_score)}


def _validation_floors(plain: Scores, validation: list[Part] = ()) -> tuple[dict, float, bool]:
    """(each signal's floor, the noise margin, whether every floor is the signal's noise variance)
    on the validation data: the choice's scale (choice.py). Without `validation` parts the floors are
    the plain model's MSE and there is no margin."""
    from ..score import floors_of
    from .choice import noise_margin
    errors = plain.errors["validation"]
    noise = {name: validation[0].data.noise_variance(name) for name in errors} if validation else {}
    floors = floors_of(errors, noise)
    margin = noise_margin([p.samples().time for p in validation], len(floors)) if validation else 1.0
    from_noise = bool(floors) and all(floors[name] == noise.get(name) for name in floors)
    return floors, margin, from_noise


# -- candidates ---------------------------------------------------------------------------------

@dataclass
class _Context:
    model_fmu: Path
    info: object
    roles: Roles
    scoring: Scoring
    work: Path
    say: object
    budget: int                    # the NeuralFMU's loss evaluations
    seed: int
    time_budget: float | None      # wall-clock cap on the whole call, seconds
    started: float
    plain: Scores                  # the declared FMU's scores (the floors of the choice)
    aliases: dict = field(default_factory=dict)   # channel -> {output: channel}, see channel_aliases
    training: dict | None = None                  # what the NeuralFMU's training did
    progress: bool = True
    input_choice: dict | None = None              # how the ANN's channels and inputs were chosen
    ann_on_term: bool = True                      # also train an ANN that starts from the fitted term
    jobs: int = 1                                 # processes: 2 builds the NeuralFMU and calibrations beside the rest
    not_trained: dict = field(default_factory=dict)   # candidate -> why it was not trained
    failed: dict = field(default_factory=dict)        # candidate -> why it could not be built, trained or scored


def _isolated(ctx: _Context, candidate: str, build, /, *args, **kwargs):
    """What `build` returns, or None when it fails: one candidate that cannot be built, trained or
    scored is reported with its reason, and the others are still chosen among. (Positional-only:
    `build` may take a `name` of its own.)"""
    try:
        return build(*args, **kwargs)
    except Exception as exc:    # any failure of one candidate's own work is that candidate's
        ctx.failed[candidate] = _reason(exc)
        ctx.say(f"      the {candidate} candidate failed: {ctx.failed[candidate]}")
        return None


def _reason(exc: Exception) -> str:
    """One line: the message of an error of ours; the kind and message of any other."""
    text = " ".join(str(exc).split())
    return text if isinstance(exc, FmuBuilderError) else f"{type(exc).__name__}: {text}"


def _reasons(failed: dict) -> str:
    return "; ".join(f"{name}: {why}" for name, why in failed.items())


def _build_candidates(ctx: _Context, diagnosis) -> list[Candidate]:
    """The fitted term, the calibrations, the NeuralFMU and the ANN on the term. The NeuralFMU and
    the calibrations depend on none of the others: with a second core they are built in a second
    process meanwhile; the ANN on the term starts from the fitted term, so the two follow each other
    in this one."""
    wirings = _ann_wirings(ctx, diagnosis)
    channels, inputs, channel_inputs = wirings[0].channels, wirings[0].inputs, wirings[0].channel_inputs
    settings = _training_settings(ctx.roles.train[0].samples(), diagnosis, ctx.budget)
    beside = ctx.jobs > 1 and can_run_beside()
    searched = "" if len(wirings) == 1 else \
        f" after screening {len(wirings)} derivatives by their warm starts ({SCREEN_BUDGET} loss evaluations each)"
    ctx.say(f"[2/5] training a NeuralFMU: ANN on {_wiring(channels, inputs, channel_inputs)} "
            f"({ctx.budget} loss evaluations){searched}{', and calibrating, in a second process' if beside else ''} ...")
    with SideProcess("training the NeuralFMU and calibrating", _beside_work,
                     (ctx, beside, wirings, settings), {},
                     in_caller=not beside) as helper:
        candidates = _isolated(ctx, "fitted term", _term_candidate, ctx, diagnosis) or []
        term = next((c for c in candidates if c.name == "fitted term"), None)
        # refined: the ANN on the term starts from it
        fitted = term.details["fitted_term"] if term is not None else diagnosis.fitted_term
        from .term_started import NAME, term_start
        # the ANN on the term reads the inputs chosen for the term's derivative, when it is one of the ANN's
        own_inputs = dict(zip(channels, channel_inputs)).get((fitted or {}).get("channel"), inputs)
        start = term_start(fitted, own_inputs) if ctx.ann_on_term else None
        why_not = start is not None and term is not None and _at_noise_floor(ctx, term)
        if why_not:
            ctx.not_trained[NAME] = why_not
            ctx.say(f"      not training an ANN on the fitted term: {why_not}")
            start = None
        on_term = []
        if start is not None:
            ctx.say(f"[3/5] training an ANN on top of the fitted term: {start.channel} with inputs "
                    f"{', '.join(start.inputs)} ({ctx.budget} loss evaluations) ...")
            on_term.append(_isolated(ctx, NAME, _neural_candidate, ctx, [start.channel], start.inputs,
                                     _aliases_of(ctx, start.channel), settings, name=NAME, base_terms=start.terms))
        if beside:
            ctx.say("      waiting for the NeuralFMU's training and the calibration in the second process ...")
        try:
            calibrated, candidate, ctx.training, said, failed = helper.result()
        except FmuBuilderError as exc:      # the second process itself ended: its candidates are lost
            calibrated, candidate, said, failed = [], None, [], {"neural": _reason(exc), "calibrated": _reason(exc)}
    ctx.failed.update(failed)
    for line in said:
        ctx.say(line)
    return [c for c in (*candidates, *calibrated, candidate, *on_term) if c is not None]


def _at_noise_floor(ctx: _Context, candidate: Candidate) -> str | None:
    """Why no ANN is trained on top of `candidate`, or None: where every signal of it lies at the noise
    floor on the validation data (choice.at_floor), an ANN on it has nothing above the noise left to
    learn, and the choice could take it only for a score below the floor, which the noise alone gives.
    Only where every signal's floor is its noise variance (else, and without validation data, the
    floor is the plain model's MSE)."""
    from ..score import validation_score
    from .choice import at_floor
    floors, _, from_noise = _validation_floors(ctx.plain, ctx.roles.validation)
    errors = candidate.scores.errors["validation"]
    if not from_noise or not at_floor(errors, floors, [p.samples().time for p in ctx.roles.validation]):
        return None
    return (f"the {candidate.name} scores {validation_score(errors, floors):.3g} on the validation data, every "
            "signal at its noise variance within the noise's spread: nothing above the noise is left to learn")


def _term_candidate(ctx: _Context, diagnosis) -> list[Candidate]:
    """The fitted term, when the diagnosis offers one and it simulates: a list of none or one."""
    fitted = diagnosis.fitted_term
    if not (fitted and fitted.get("offered")):
        return []
    ctx.say(f"[2/5] fitting the term: the diagnosis' {fitted['expression']}, and the forms of its leading "
            "variables ...")
    noise = {e.signal: e.noise for e in diagnosis.errors}
    term = _fitted_term_candidate(ctx, diagnosis, _aliases_of(ctx, fitted["channel"]), noise)
    return [] if term is None else [term]


def _beside_work(ctx: _Context, beside: bool, *args, **kwargs) -> tuple[list[Candidate], Candidate, dict, list[str]]:
    """The NeuralFMU candidate and the calibrated ones, what the training did (ctx.training) and
    what they had to say. In a second process it keeps its messages for the caller and shows no
    progress bars, which would cross the caller's. The candidates' scores' runs are keyed by
    id(data): the forked process's data objects are the caller's, at the same addresses."""
    said = []
    if beside:
        ctx = replace(ctx, say=said.append, progress=False)
        set_progress_enabled(False)     # this process's bars only
    neural = _isolated(ctx, "neural", _searched_neural_candidate, ctx, *args, **kwargs)
    calibrated = _isolated(ctx, "calibrated", _calibrated_candidates, ctx) or []
    return calibrated, neural, ctx.training, said, ctx.failed


def _candidate(ctx: _Context, name: str, description: str, fmu: Path, folder: Path, details: dict) -> Candidate:
    scores = Scores(fmu)
    score(scores, ctx.roles, ctx.scoring, ("train", "validation"), f"scoring the {name} hybrid")
    return Candidate(name, description, fmu, folder, scores, details)


def _aliases_of(ctx: _Context, channel: str) -> dict[str, str]:
    if channel not in ctx.aliases:
        data = ctx.roles.train[0].samples()
        start = float(data.time[0])
        ctx.aliases[channel] = channel_aliases(ctx.model_fmu, ctx.info, channel, ctx.roles.train[0].start_values, data.time,
                                               start, min(float(data.time[-1]), start + ALIAS_SPAN),
                                               inputs=data.inputs)
        if ctx.aliases[channel]:
            ctx.say(f"      corrected with {channel} too: {', '.join(ctx.aliases[channel])} (equal to it in the model)")
    return ctx.aliases[channel]


def channel_aliases(model_fmu, info, channel: str, start_values: dict, data_time, start: float,
                    stop: float, inputs: dict | None = None) -> dict[str, str]:
    """{output: channel} for the outputs of the plain model equal to `channel` along its run
    (the diagnosis' test: within 1e-9 relative), e.g. a power whose integral is an energy state.
    The hybrid must correct them with the derivative, or they contradict the corrected state.
    inputs: the data's FMU input columns at `data_time`, which drive the run."""
    from ..diagnose.diagnosis import derivative_aliases
    from ..diagnose.runs import ModelRunner
    states = {s.name for s in info.states}
    outputs = [v.name for v in info.outputs
               if v.type == "Real" and v.variability == "continuous" and v.name not in states]
    if not outputs:
        return {}
    runner = ModelRunner(model_fmu, start_values=start_values, data_time=np.asarray(data_time), start=start,
                         stop=stop, measured=[], recorded=[*outputs, channel], inputs=inputs)
    try:
        run = runner.simulate()
    finally:
        runner.close()
    index = info.state_index(channel)
    # An output that stays 0 matches any derivative that does: not evidence of an alias.
    return {name: channel for name, channels in derivative_aliases(info, run, outputs).items()
            if index in channels and np.any(run.trajectories[name] != 0.0)}


@dataclass
class _Wiring:
    """A NeuralFMU's derivatives, the variables its ANN reads (per derivative) and how they were chosen."""
    channels: list[str]
    inputs: list[str]
    channel_inputs: list[list[str]]
    aliases: dict
    choice: dict


def _ann_wirings(ctx: _Context, diagnosis) -> list[_Wiring]:
    """The NeuralFMU's wiring for each derivative the search tries (_channel_options), inputs chosen
    as for the traced one; duplicates dropped."""
    wirings = []
    for channel in _channel_options(ctx.info, diagnosis):
        further = list(diagnosis.ambiguous_channels) if channel == diagnosis.channel else []
        channels, inputs, channel_inputs, choice = _ann_channels_and_inputs(ctx, diagnosis, channel, further)
        aliases = {name: c for ch in channels for name, c in _aliases_of(ctx, ch).items()}
        wiring = _Wiring(channels, inputs, channel_inputs, aliases, choice)
        if all((w.channels, w.inputs) != (channels, inputs) for w in wirings):
            wirings.append(wiring)
    return wirings


def _channel_options(info, diagnosis) -> list[str]:
    """The derivatives the diagnosis cannot rule out, the traced one first: those whose change moved
    a measured signal in its screening (a positive score), by score; every derivative when it did not
    screen them (no tracing); at most SEARCH_CHANNELS."""
    scored = sorted((c for c, score in diagnosis.channel_scores.items() if score > 0),
                    key=lambda c: -diagnosis.channel_scores[c])
    options = scored or [d.name for d in info.derivatives]
    if diagnosis.channel is not None:
        options = [diagnosis.channel, *(c for c in options if c != diagnosis.channel)]
    return options[:SEARCH_CHANNELS]


def _ann_channels_and_inputs(ctx: _Context, diagnosis, channel: str, further: list[str]):
    """The derivatives the ANN corrects (`channel` and those of `further` the inputs explain), the
    variables it reads, per derivative those its correction reads, and how they were chosen: on
    held-out error (hybridize.inputs); the diagnosis' leading variables when that choice has nothing
    to go on."""
    from .inputs import choose_ann
    choice = choose_ann(ctx.model_fmu, ctx.info, ctx.roles.train, ctx.roles.validation, channel,
                        further, ctx.scoring.step, ctx.scoring.solver)
    if choice is None:
        inputs = _ann_inputs(diagnosis, ctx.info, channel)
        return [channel], inputs, [inputs], {
            "rule": "the diagnosis' leading variable, or the measured states without one (the channel's state is "
                    "not measured, or no variable predicted its estimated missing term under cross-validation "
                    "beyond the noise)"}
    seen_in = f" (on the missing term of {choice.through.channel}, where the loop's compensation shows)" \
        if choice.through is not None else ""
    ctx.say(f"      ANN inputs for {channel} chosen by cross-validation on the training and validation data{seen_in}: "
            f"{', '.join(choice.inputs)}")
    return choice.channels, choice.inputs, choice.channel_inputs, choice.to_dict()


def _wiring(channels: list[str], inputs: list[str], channel_inputs: list[list[str]]) -> str:
    """'der(a) with inputs x, y', or per channel when they read different inputs."""
    if all(list(names) == list(inputs) for names in channel_inputs):
        return f"{', '.join(channels)} with inputs {', '.join(inputs)}"
    return "; ".join(f"{c} with inputs {', '.join(names)}" for c, names in zip(channels, channel_inputs))


def _ann_inputs(diagnosis, info, channel: str) -> list[str]:
    """The leading traced variables that an ANN can read (Real FMU variables, not time), or without
    them the measured states: what the missing term most plausibly depends on."""
    usable = [name for name in diagnosis.inputs
              if name in info.variables and info.variables[name].type == "Real" and name != channel]
    if not usable:
        states = {s.name for s in info.states}
        usable = [e.signal for e in diagnosis.errors if e.signal in states] or sorted(states)
    if not usable:
        raise FmuBuilderError(f"the diagnosis named no FMU variable the ANN at {channel} could read")
    return usable[:MAX_ANN_INPUTS]


def _fitted_term_candidate(ctx: _Context, diagnosis, aliases: dict[str, str],
                           noise: dict[str, float]) -> Candidate | None:
    """The fitted term in the form the validation data choose among the leading variables' forms,
    each fitted through the simulation of the training runs (hybridize/term_forms.py), exported as a
    hybrid, its coefficients' common scale refined through the simulation on the training data
    (hybridize/refine_term.py) when that lowers the training error."""
    from .choice import noise_margin
    from .refine_term import coefficients_text, refine_scales, scaled_term, term_gates
    from .term_forms import candidate_forms, choose_form, fit_forms, fitted_term_of, label_of
    fitted = diagnosis.fitted_term
    runs = [(p.samples(), p.start_values) for p in ctx.roles.train]
    fits = fit_forms(ctx.model_fmu, fitted["channel"], candidate_forms(diagnosis), runs, ctx.roles.validation,
                     ctx.scoring, noise, aliases, show=ctx.progress)
    margin = noise_margin([p.samples().time for p in ctx.roles.validation], len(ctx.roles.train[0].data.names))
    form = choose_form(fits, margin)
    if form is not None:
        fitted = fitted_term_of(fitted, form.terms)
        kept = "the diagnosis' form kept" if form.label == label_of(diagnosis.fitted_term["terms"]) \
            else "another form chosen"
        ctx.say(f"      {len(fits)} forms fitted through the simulation, {kept} on the validation data "
                f"(margin x{margin:.3g}): {fitted['expression']}")
    diagnosed = _export_fitted_term(ctx, fitted, aliases, "fitted_term_diagnosed")
    if diagnosed is None:
        return None
    spec, fmu = diagnosed
    refinement = refine_scales(fmu, term_gates(spec), runs, noise, ctx.scoring.step,
                               show=ctx.progress)
    term = fitted
    if refinement.kept:
        term = scaled_term(fitted, refinement.scales[0])
        spec, fmu = _export_fitted_term(ctx, term, aliases, "fitted_term")
        ctx.say(f"      coefficient refined through the simulation: {coefficients_text(fitted)} -> "
                f"{coefficients_text(term)} ({refinement.simulations} simulations)")
    else:
        ctx.say(f"      coefficient kept: the refinement through the simulation did not lower the training "
                f"error ({refinement.simulations} simulations)")
    return _candidate(ctx, "fitted term", term["expression"], fmu, spec.onnx.parent,
                      {"expression": term["expression"], "aliases": aliases, "fitted_on": ctx.roles.train[0].label,
                       "fitted_term": term, "forms": {
                           "chosen": form.label if form is not None else None, "margin": margin,
                           "fitted": [f.to_dict() for f in fits]}, "refinement": {
                           **refinement.to_dict(), "coefficients_before": coefficients_text(fitted),
                           "coefficients_after": coefficients_text(term),
                           "refined_on": [p.label for p in ctx.roles.train]}})


def _export_fitted_term(ctx: _Context, fitted: dict, aliases: dict[str, str], name: str):
    """(spec, hybrid FMU) of a fitted term, or None when an FMU cannot read its variable (time)."""
    from ..export import export_hybrid
    from .terms import spec_from_fitted_term
    folder = ctx.work / name
    folder.mkdir()
    spec = spec_from_fitted_term(fitted, ctx.model_fmu, ctx.info.guid, folder, aliases)
    if spec is None:
        return None
    return spec, export_hybrid(spec, folder / "hybrid.fmu")


def _calibrated_candidates(ctx: _Context) -> list[Candidate]:
    """One candidate per calibrated parameter: the original FMU with the value fitted on the training data."""
    from .calibrate import calibrate
    ctx.say("[2/5] screening the FMU's parameters for one that explains the residual ...")
    ranked, fits = calibrate(ctx.model_fmu, ctx.info, [(p.samples(), p.start_values) for p in ctx.roles.train],
                             ctx.scoring, say=ctx.say)
    candidates = []
    for index, fit in enumerate(fits):
        candidates.append(_isolated(ctx, f"calibrated {fit.name}", _calibrated_candidate, ctx, fit, ranked,
                                    ctx.work / f"calibrated_{index}"))
    return [c for c in candidates if c is not None]


def _calibrated_candidate(ctx: _Context, fit, ranked, folder: Path) -> Candidate:
    """The original with the fitted value: a hybrid with one override and no network."""
    from ..export import HybridSpec, export_hybrid
    folder.mkdir()
    spec = HybridSpec.calibration(ctx.model_fmu, {fit.name: fit.value})
    spec.save(folder / "spec.json")
    fmu = export_hybrid(spec, folder / "hybrid.fmu")
    return _candidate(ctx, f"calibrated {fit.name}", fit.description, fmu, folder,
                      fit.details(ranked, ctx.roles.train[0].label))


def _searched_neural_candidate(ctx: _Context, wirings: list[_Wiring], settings) -> Candidate:
    """The NeuralFMU on the derivative the validation data choose: each wiring screened with
    SCREEN_BUDGET loss evaluations (its warm start included), the best validation score trained with
    the full budget. One wiring: trained at once."""
    screening = []
    if len(wirings) > 1:
        for k, wiring in enumerate(wirings):
            trained = _train_neural(ctx, wiring.channels, wiring.inputs, wiring.aliases, settings,
                                    f"screen_{k}", channel_inputs=wiring.channel_inputs, budget=SCREEN_BUDGET)
            trained.model.close()
            summary = trained.metrics.get("validation") or {}
            screening.append({"channels": wiring.channels, "inputs": wiring.inputs,
                              "validation_score": summary.get("best_score", float("inf"))})
            ctx.say(f"      screened {_wiring(wiring.channels, wiring.inputs, wiring.channel_inputs)}: validation "
                    f"score {screening[-1]['validation_score']:.4g}")
    best = wirings[min(range(len(wirings)), key=lambda k: screening[k]["validation_score"]) if screening else 0]
    ctx.input_choice = best.choice
    candidate = _neural_candidate(ctx, best.channels, best.inputs, best.aliases, settings,
                                  channel_inputs=best.channel_inputs)
    candidate.details["channel_search"] = {"screened": screening, "budget_each": SCREEN_BUDGET} if screening else None
    return candidate


def _work_folder(ctx: _Context, name: str) -> Path:
    """Where the candidate `name` keeps its training and export."""
    return ctx.work / name.replace(" ", "_")


def _train_neural(ctx: _Context, channels: list[str], inputs: list[str], aliases: dict[str, str], settings,
                  name: str, base_terms: list[dict] = (), channel_inputs: list[list[str]] = (), budget: int | None = None):
    """A NeuralFMU trained on the first training run, checkpointed on the validation data."""
    from ..neural import train_neural_fmu
    from ..neural.train import Validation
    folder = _work_folder(ctx, name)
    folder.mkdir()
    first = ctx.roles.train[0]
    cap = None if ctx.time_budget is None else max(1.0, ctx.time_budget - (time.perf_counter() - ctx.started))
    budget = ctx.budget if budget is None else budget
    # The training sees the model through the data's sensor lag (from the sidecar), at the step and
    # with the solver every model is scored with, and the outputs equal to a corrected derivative
    # through it, as the exported hybrid shows them.
    # Each ANN candidate ends with its best epoch on the validation data, in the score the choice
    # makes (score.py), the start included: an ANN on a fitted term is never worse there than the
    # term, a NeuralFMU never worse than its warm start.
    held_out = ctx.roles.validation[0]
    validation = Validation(held_out.data, held_out.window, held_out.start_values)
    if budget != ctx.budget:      # a screening: its warm start and first steps, no last-layer refinement
        settings = replace(settings, budget=budget, last_layer_simulations=0)
    settings = replace(settings, seed=ctx.seed, time_budget=cap, solver=ctx.scoring.solver,
                       step_size=ctx.scoring.step, progress=ctx.progress, aliases=dict(aliases))
    return train_neural_fmu(ctx.model_fmu, first.samples(), targets=channels, inputs=inputs,
                            start_values=first.start_values, topology="residual",
                            base_terms=base_terms, channel_inputs=channel_inputs, validation=validation,
                            settings=settings, output=folder / "trained.neuralfmu")


def _neural_candidate(ctx: _Context, channels: list[str], inputs: list[str], aliases: dict[str, str],
                      settings, name: str = "neural", base_terms: list[dict] = (),
                      channel_inputs: list[list[str]] = ()) -> Candidate:
    """A trained NeuralFMU exported as a hybrid; with base_terms its ANN adds to that fitted term.
    channel_inputs: per channel the inputs its correction reads (empty: all)."""
    channel_inputs = [list(names) for names in channel_inputs] or [list(inputs) for _ in channels]
    from ..export import export_hybrid
    from .terms import spec_from_neural
    first = ctx.roles.train[0]
    trained = _train_neural(ctx, channels, inputs, aliases, settings, name, base_terms, channel_inputs)
    folder = _work_folder(ctx, name)
    try:
        spec = spec_from_neural(trained.model, folder, aliases)
    finally:
        trained.model.close()
    fmu = export_hybrid(spec, folder / "hybrid.fmu")
    metrics = trained.metrics
    if not base_terms:         # the report's training summary is the plain NeuralFMU's
        optimizer = {"adam": "Adam", "lbfgs": "L-BFGS"}[settings.optimizer]
        ctx.training = {"budget": ctx.budget, "loss_evaluations": metrics.get("loss_evaluations"),
                        "steps": metrics.get("epochs"), "optimizer": optimizer, "seed": ctx.seed,
                        "time_budget": ctx.time_budget,
                        "cut_short_by_time_budget": bool(metrics.get("cut_short_by_time_budget")),
                        "at_noise_floor": metrics.get("at_noise_floor"), "trained_on": first.label,
                        **_reproduction(ctx, channels, inputs, aliases, channel_inputs, metrics["settings"])}
    details = {"channel": ", ".join(channels), "channels": channels, "inputs": inputs,
               "channel_inputs": dict(zip(channels, channel_inputs)), "aliases": aliases,
               "steps": metrics.get("epochs"), "loss_evaluations": metrics.get("loss_evaluations"),
               "training_seconds": metrics.get("seconds"),
               "loss_signals": settings.loss_signals, "trained_on": first.label,
               "input_choice": ctx.input_choice if not base_terms else None,
               "warm_start": metrics.get("warm_start"), "last_layer": metrics.get("last_layer"),
               "at_noise_floor": metrics.get("at_noise_floor"), "validation_checkpoint": metrics.get("validation")}
    description = f"ANN on {_wiring(channels, inputs, channel_inputs)}"
    if base_terms:
        description += " added to the fitted term"
    return _candidate(ctx, name, description, fmu, folder, details)


def _training_settings(data: MeasuredData, diagnosis, budget: int):
    """The NeuralFMU training's settings (recipe.py) on `data`: the loss is on the signals in which
    the diagnosis found the effect (all of them if it found it in none alone). The others sit at the
    noise level and their fit to noise pulls the ANN away from the effect."""
    from .recipe import recipe_settings
    showing = [e.signal for e in diagnosis.errors if e.significant]
    return recipe_settings(data.time, showing or None, budget)


# The settings a user passes to `fmubuilder train` to repeat a training (the rest: the run's, or the
# command line's own, such as progress bars).
RUN_SETTINGS = ("epochs", "checkpoint", "resume", "progress", "threads", "time_budget")


def _reproduction(ctx: _Context, channels: list[str], inputs: list[str], aliases: dict[str, str],
                  channel_inputs: list[list[str]], settings: dict) -> dict:
    """The NeuralFMU's training settings and the `fmubuilder train` command that trains the same
    network, or None with why not."""
    first = ctx.roles.train[0]
    why_not = _not_repeatable(ctx, first, inputs, channel_inputs)
    recipe = {name: value for name, value in settings.items() if name not in RUN_SETTINGS}
    return {"settings": recipe, "command": None if why_not else _train_command(ctx, first, channels, inputs, aliases,
                                                                                  settings),
            "command_not_given": why_not}


def _not_repeatable(ctx: _Context, first: Part, inputs: list[str], channel_inputs: list[list[str]]) -> str | None:
    if not ctx.roles.held_out_of_training:
        return "the validation was a separate run, and the recipe holds out the late share of the training run"
    if first.data.noise_estimate:
        return "the noise of signals without a spread column was estimated by the diagnosis"
    if any(list(names) != list(inputs) for names in channel_inputs):
        return "the derivatives read different inputs"
    return None


def _train_command(ctx: _Context, first: Part, channels: list[str], inputs: list[str], aliases: dict[str, str],
                   settings: dict) -> str:
    """`fmubuilder train --recipe hybridize` with this run's data, wiring, budget and seed."""
    import shlex
    words = ["fmubuilder", "train", str(ctx.model_fmu), "--data", str(first.data.path), "--recipe", "hybridize",
             *(w for c in channels for w in ("--target", c)), "--inputs", ",".join(inputs),
             "--budget", str(ctx.budget), "--seed", str(ctx.seed)]
    if settings["loss_signals"]:
        words += ["--loss", ",".join(settings["loss_signals"])]
    words += [w for output, channel in aliases.items() for w in ("--alias", f"{output}={channel}")]
    sidecar = first.data.start_values
    words += [w for name, value in first.start_values.items() if sidecar.get(name) != value
              for w in ("--start", f"{name}={value!r}" if isinstance(value, float) else f"{name}={value}")]
    return " ".join(shlex.quote(w) for w in [*words, "-o", "trained.neuralfmu"])


def _roundtrip(chosen: Candidate, test: Part) -> dict:
    """The round trip of the chosen FMU over the start of the test data: the hybrid in fmpy and the
    engine against the Python reference (the original with the network or term and the overrides)."""
    from ..export import validate_hybrid
    data = test.data
    stop = min(data.stop, data.start + ROUNDTRIP_SPAN)
    report = validate_hybrid(chosen.fmu, spec=chosen.spec_dir / "spec.json", start_values=test.start_values,
                             stop_time=stop)
    rows = [c for c in report.comparisons if not c.informational and c.compared]
    return {"passed": report.passed, "max_rel_error": max((c.max_rel for c in rows), default=None),
            "span": [data.start, stop], "table": report.format_table(),
            "not_compared": [c.label for c in report.comparisons if c.error is None and not c.compared]}


def _publish(source: Path, target: Path, force: bool) -> None:
    refuse_existing(target, force)     # again: the file may have appeared while the command ran
    target.parent.mkdir(parents=True, exist_ok=True)
    copy_atomically(source, target)


def _check_outputs(output_fmu: Path, report_dir: Path, force: bool) -> None:
    refuse_existing(output_fmu, force)
    if report_dir.exists() and any(report_dir.iterdir()) and not force:
        raise FmuBuilderError(f"report folder {report_dir} is not empty; choose another with --report or pass --force")


def _diagnosis_line(diagnosis) -> str:
    if not diagnosis.significant:
        return f"no significant effect (joint p = {diagnosis.p_value:.3g})"
    if diagnosis.channel is None:
        return (f"significant effect (joint p = {diagnosis.p_value:.3g}), no term form traced it to one derivative: "
                "the NeuralFMU's search decides")
    return (f"significant effect (joint p = {diagnosis.p_value:.3g}), traced to {diagnosis.channel}; "
            f"inputs: {', '.join(diagnosis.inputs[:3])}")
