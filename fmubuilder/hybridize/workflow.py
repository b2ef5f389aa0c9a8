"""`fmubuilder hybridize`: diagnose, add the effect, train, export, validate, report.

    diagnosis  -> is there an effect beyond noise? which derivative, which variables?
    candidates -> a NeuralFMU with the ANN at the traced channel and inputs, and the fitted
                  symbolic term when the diagnosis offers one; each exported as a hybrid FMU
    selection  -> the candidate with the lower error on the held-out data
    validation -> round trip of the chosen hybrid FMU (fmpy vs the Python reference)
    report     -> DIR/report.json, DIR/report.md and plots
"""
from __future__ import annotations

import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import FmuBuilderError
from ..files import copy_atomically
from ..fmi import read_model_info
from .evaluate import Evaluation, evaluate, load_data, relative_mse

# Share of the time budget for the diagnosis' tracing. The NeuralFMU's training gets what is left
# after keeping back, for the steps after it (export, two evaluations, validation, report), twice
# the plain model's evaluation time plus AFTER_TRAINING seconds; at least MIN_TRAINING seconds.
DIAGNOSIS_SHARE = 0.2
AFTER_TRAINING = 30.0
MIN_TRAINING = 30.0
# Seconds of the test data replayed by the round-trip validation (fmpy Euler and CVode).
VALIDATION_SPAN = 60.0
# ANN inputs: the leading traced variable. Each further input is another way to fit noise, and the
# runners-up often carry little new (on the VLDM, motor_torque_limit is a function of speed).
MAX_ANN_INPUTS = 1
# NeuralFMU training: the data cut into elements of at most MAX_ELEMENT_LENGTH seconds (at least
# MIN_ELEMENTS of them), all simulated side by side in one batch: one optimizer step per epoch, which
# lets the training rewind an epoch that made the loss worse (see neural.train.Trainer._keep_best).
MAX_ELEMENT_LENGTH = 100.0
MIN_ELEMENTS = 8
# Seconds of the training data on which outputs equal to the corrected derivative are detected.
ALIAS_SPAN = 60.0


@dataclass
class Candidate:
    name: str                      # "neural" or "fitted term"
    description: str
    fmu: Path
    spec_dir: Path
    train: Evaluation
    test: Evaluation
    details: dict = field(default_factory=dict)


@dataclass
class HybridizeResult:
    report: dict
    report_dir: Path
    hybrid_fmu: Path | None


def hybridize(model_fmu, train_csv, test_csv, output_fmu, report_dir, *, train_start: dict | None = None,
              test_start: dict | None = None, time_budget: float = 300.0, force: bool = False,
              progress: bool = True) -> HybridizeResult:
    started = time.perf_counter()
    model_fmu, output_fmu, report_dir = Path(model_fmu), Path(output_fmu), Path(report_dir)
    _check_outputs(output_fmu, report_dir, force)
    info = read_model_info(model_fmu)
    train_data, test_data = load_data(Path(train_csv), model_fmu), load_data(Path(test_csv), model_fmu)
    train_start = {**train_data.start_values, **(train_start or {})}
    test_start = {**test_data.start_values, **(test_start or {})}
    work = Path(tempfile.mkdtemp(prefix="fmubuilder-hybridize-"))
    try:
        report_dir.mkdir(parents=True, exist_ok=True)
        say = print if progress else (lambda *a, **k: None)
        say(f"[1/5] diagnosing {model_fmu.name} against {Path(train_csv).name} ...")
        from ..diagnose import diagnose
        diagnosis = diagnose(model_fmu, train_csv, train_start, plots_dir=report_dir / "diagnosis",
                             time_budget=DIAGNOSIS_SHARE * time_budget)
        train_start = {**train_start, **diagnosis.start_values}
        say(f"      {_diagnosis_line(diagnosis)}")
        timings = {"diagnosis": time.perf_counter() - started}
        evaluation_started = time.perf_counter()
        before_train = evaluate(model_fmu, train_data, train_start)
        before_test = evaluate(model_fmu, test_data, test_start)
        evaluation_seconds = timings["evaluation"] = time.perf_counter() - evaluation_started
        candidates: list[Candidate] = []
        if diagnosis.significant or force:
            if diagnosis.channel is None:
                raise FmuBuilderError("the diagnosis found an effect but could not trace it to a state derivative; "
                                      "see the diagnosis in the report folder")
            context = _Context(model_fmu, info, train_csv, test_csv, train_data, test_data, train_start, test_start,
                               work, say, evaluation_seconds, progress=progress)
            candidates_started = time.perf_counter()
            candidates = _build_candidates(context, diagnosis, started, time_budget)
            timings["candidates"] = time.perf_counter() - candidates_started
        chosen = _choose(candidates, before_test)
        hybrid_path, roundtrip = None, None
        if chosen is not None:
            say(f"[4/5] validating the round trip of the {chosen.name} hybrid ...")
            validation_started = time.perf_counter()
            roundtrip = _validate(chosen, test_csv, test_start, test_data)
            timings["validation"] = time.perf_counter() - validation_started
            _publish(chosen.fmu, output_fmu, force)
            hybrid_path = output_fmu
        say("[5/5] writing the report ...")
        from .report import write_report
        report = write_report(report_dir, model_fmu=model_fmu, diagnosis=diagnosis, before=(before_train, before_test),
                              candidates=candidates, chosen=chosen, roundtrip=roundtrip, hybrid_fmu=hybrid_path,
                              train_data=train_data, test_data=test_data, seconds=time.perf_counter() - started,
                              timings=timings)
        return HybridizeResult(report, report_dir, hybrid_path)
    finally:
        shutil.rmtree(work, ignore_errors=True)


@dataclass
class _Context:
    model_fmu: Path
    info: object
    train_csv: Path
    test_csv: Path
    train_data: object
    test_data: object
    train_start: dict
    test_start: dict
    work: Path
    say: object
    evaluation_seconds: float      # of the plain model on the training and the held-out data
    aliases: dict = field(default_factory=dict)   # channel -> {output: channel}, see channel_aliases
    progress: bool = True


def _build_candidates(ctx: _Context, diagnosis, started: float, time_budget: float) -> list[Candidate]:
    candidates = []
    fitted = diagnosis.fitted_term
    if fitted and fitted.get("offered"):
        ctx.say(f"[2/5] exporting the fitted term: {fitted['expression']}")
        term = _fitted_term_candidate(ctx, fitted, _aliases_of(ctx, fitted["channel"]))
        if term is not None:
            candidates.append(term)
    inputs = _ann_inputs(diagnosis, ctx.info)
    aliases = _aliases_of(ctx, diagnosis.channel)
    remaining = time_budget - (time.perf_counter() - started)
    budget = max(MIN_TRAINING, remaining - 2.0 * ctx.evaluation_seconds - AFTER_TRAINING)
    ctx.say(f"[3/5] training a NeuralFMU: ANN on {diagnosis.channel} with inputs {', '.join(inputs)} "
            f"(time budget {budget:.0f} s) ...")
    settings = _training_settings(ctx.train_data, diagnosis)
    candidates.append(_neural_candidate(ctx, diagnosis.channel, inputs, budget, aliases, settings))
    return candidates


def _aliases_of(ctx: _Context, channel: str) -> dict[str, str]:
    if channel not in ctx.aliases:
        data = ctx.train_data
        start = float(data.time[0])
        ctx.aliases[channel] = channel_aliases(ctx.model_fmu, ctx.info, channel, ctx.train_start, data.time,
                                               start, min(float(data.time[-1]), start + ALIAS_SPAN))
        if ctx.aliases[channel]:
            ctx.say(f"      corrected with {channel} too: {', '.join(ctx.aliases[channel])} (equal to it in the model)")
    return ctx.aliases[channel]


def channel_aliases(model_fmu, info, channel: str, start_values: dict, data_time, start: float,
                    stop: float) -> dict[str, str]:
    """{output: channel} for the outputs of the plain model equal to `channel` along its run
    (the diagnosis' test: within 1e-9 relative), e.g. a power whose integral is an energy state.
    The hybrid must correct them with the derivative, or they contradict the corrected state."""
    import numpy as np
    from ..diagnose.diagnosis import derivative_aliases
    from ..diagnose.runs import ModelRunner
    states = {s.name for s in info.states}
    outputs = [v.name for v in info.outputs
               if v.type == "Real" and v.variability == "continuous" and v.name not in states]
    if not outputs:
        return {}
    runner = ModelRunner(model_fmu, start_values=start_values, data_time=np.asarray(data_time), start=start,
                         stop=stop, measured=[], recorded=[*outputs, channel])
    try:
        run = runner.simulate()
    finally:
        runner.close()
    index = info.state_index(channel)
    # An output that stays 0 matches any derivative that does: not evidence of an alias.
    return {name: channel for name, channels in derivative_aliases(info, run, outputs).items()
            if index in channels and np.any(run.trajectories[name] != 0.0)}


def _ann_inputs(diagnosis, info) -> list[str]:
    """The leading traced variables that an ANN can read (Real FMU variables, not time)."""
    usable = [name for name in diagnosis.inputs
              if name in info.variables and info.variables[name].type == "Real" and name != diagnosis.channel]
    if not usable:
        raise FmuBuilderError(f"the diagnosis named no FMU variable the ANN at {diagnosis.channel} could read")
    return usable[:MAX_ANN_INPUTS]


def _fitted_term_candidate(ctx: _Context, fitted: dict, aliases: dict[str, str]) -> Candidate | None:
    from ..export import export_hybrid
    from .terms import spec_from_fitted_term
    folder = ctx.work / "fitted_term"
    folder.mkdir()
    spec = spec_from_fitted_term(fitted, ctx.model_fmu, ctx.info.guid, folder, aliases)
    if spec is None:
        return None
    fmu = export_hybrid(spec, folder / "hybrid.fmu")
    return Candidate("fitted term", fitted["expression"], fmu, folder,
                     evaluate(fmu, ctx.train_data, ctx.train_start), evaluate(fmu, ctx.test_data, ctx.test_start),
                     {"expression": fitted["expression"], "aliases": aliases})


def _neural_candidate(ctx: _Context, channel: str, inputs: list[str], budget: float,
                      aliases: dict[str, str], settings: dict) -> Candidate:
    from ..export import export_hybrid
    from ..neural import train_neural_fmu
    from .terms import spec_from_neural
    folder = ctx.work / "neural"
    folder.mkdir()
    # The data's sidecar gives the bench's sensor lag; the training sees the model through it.
    trained = train_neural_fmu(ctx.model_fmu, ctx.train_csv, targets=[channel], inputs=inputs,
                               start_values=ctx.train_start, topology="residual", time_budget=budget,
                               output=folder / "trained.neuralfmu", progress=ctx.progress,
                               **settings)
    try:
        spec = spec_from_neural(trained.model, folder, aliases)
    finally:
        trained.model.close()
    fmu = export_hybrid(spec, folder / "hybrid.fmu")
    details = {"channel": channel, "inputs": inputs, "aliases": aliases, "epochs": trained.metrics.get("epochs"),
               "training_seconds": trained.metrics.get("seconds"), "loss_signals": settings["loss_signals"]}
    return Candidate("neural", f"ANN on {channel} with inputs {', '.join(inputs)}", fmu, folder,
                     evaluate(fmu, ctx.train_data, ctx.train_start), evaluate(fmu, ctx.test_data, ctx.test_start),
                     details)


def _training_settings(data, diagnosis) -> dict:
    """Element length and loss signals of the NeuralFMU training: the loss is on the signals in
    which the diagnosis found the effect (all of them if it found it in none alone). The others sit
    at the noise level and their fit to noise pulls the ANN away from the effect."""
    span = float(data.time[-1] - data.time[0])
    showing = [e.signal for e in diagnosis.errors if e.significant]
    return {"element_length": min(MAX_ELEMENT_LENGTH, span / MIN_ELEMENTS), "loss_signals": showing or None}


def _choose(candidates: list[Candidate], before_test: Evaluation) -> Candidate | None:
    """The candidate with the lowest held-out error, if it improves on the plain model."""
    scored = [(relative_mse(before_test.errors, c.test.errors), c) for c in candidates]
    scored = [(score, c) for score, c in scored if score < 1.0]
    return min(scored, key=lambda sc: sc[0])[1] if scored else None


def _validate(chosen: Candidate, test_csv, test_start: dict, test_data) -> dict:
    from ..export import validate_hybrid
    stop = min(float(test_data.time[-1]), float(test_data.time[0]) + VALIDATION_SPAN)
    report = validate_hybrid(chosen.fmu, spec=chosen.spec_dir / "spec.json", start_values=test_start,
                             stop_time=stop)
    rows = [c for c in report.comparisons if not c.informational and c.error is None]
    return {"passed": report.passed, "max_rel_error": max((c.max_rel for c in rows), default=None),
            "span": [float(test_data.time[0]), stop], "table": report.format_table()}


def _publish(source: Path, target: Path, force: bool) -> None:
    if target.exists() and not force:
        raise FmuBuilderError(f"{target} exists; choose another output path or pass --force to overwrite it")
    target.parent.mkdir(parents=True, exist_ok=True)
    copy_atomically(source, target)


def _check_outputs(output_fmu: Path, report_dir: Path, force: bool) -> None:
    if output_fmu.exists() and not force:
        raise FmuBuilderError(f"{output_fmu} exists; choose another output path or pass --force to overwrite it")
    if report_dir.exists() and any(report_dir.iterdir()) and not force:
        raise FmuBuilderError(f"report folder {report_dir} is not empty; choose another with --report or pass --force")


def _diagnosis_line(diagnosis) -> str:
    if not diagnosis.significant:
        return f"no significant effect (joint p = {diagnosis.p_value:.3g})"
    return (f"significant effect (joint p = {diagnosis.p_value:.3g}), traced to {diagnosis.channel}; "
            f"inputs: {', '.join(diagnosis.inputs[:3])}")
