"""Draw one effect-zoo case from an integer seed and write it as a folder hybridize can run on.

A case is a truth (a declared base FMU plus, at random, a missing effect, a wrong parameter, or
nothing) and data measured on it. Written per case:

    declared.fmu            the model the user has
    truth.fmu               the truth (effects only: the declared FMU wrapped by fmubuilder.export,
                            its channel adding the effect as a small ONNX graph)
    train.csv (+ .json)     training data, the sidecar holding the run's start values
    validation.csv (+ .json) a separate validation run (about half the seeds)
    test.csv (+ .json)      test data: another excitation
    truth.json              what the truth is and the true noise variance of every measured column

The size: the plain (declared) FMU's test MSE on its most affected signal is drawn log-uniform in
10..10^4 times that signal's noise variance (of the measured value: a mean over runs has the
variance of one run over the number of runs); the noise is set from that target, not the effect.
"""
from __future__ import annotations

import json
import math
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .bases import BASES, Base, Run
from .effects import FAMILIES, Effect, Part

NO_EFFECT_SHARE = 0.1          # of seeds: truth = declared model (the false-publish rate's cases)
PARAMETER_SHARE = 0.2          # of seeds: a wrong parameter, no missing term
RATIO_RANGE = (10.0, 1e4)      # plain test MSE / noise variance of the most affected signal
RATE_RANGE = (5.0, 100.0)      # Hz
TRUTH_RTOL = 1e-8              # far below any noise drawn here
MAX_ATTEMPTS = 5               # draws of a truth before a seed fails
CHECK_POINTS = 25              # states at which the truth's derivatives are checked


# -- simulation at given time stamps --------------------------------------------------------------

def simulate_at(fmu: Path, stamps: np.ndarray, names: list[str], start_values: dict | None = None,
                inputs: dict[str, np.ndarray] | None = None, rtol: float = TRUTH_RTOL) -> dict[str, np.ndarray]:
    """Values of `names` at the stamps; inputs are given at the stamps (linear between them, as the
    data file's input columns drive the FMU in every fmubuilder stage)."""
    from fmubuilder.fmi.instance import Fmu
    from fmubuilder.simulation import FmuSystem, input_signals_from, make_solver, run
    with Fmu(fmu) as loaded:
        signals = input_signals_from({"time": stamps, **inputs}, loaded.info) if inputs else None
        solver = make_solver("dopri5", rtol=rtol, atol=1e-10, max_step=(stamps[-1] - stamps[0]) / 50)
        system = FmuSystem(loaded, variables=names, start_values=dict(start_values or {}), inputs=signals,
                           tolerance=rtol)
        try:
            result = run(system, solver, start_time=float(stamps[0]), stop_time=float(stamps[-1]),
                         output_times=stamps)
        finally:
            system.close()
    if result.terminated_early:
        raise RuntimeError(f"{fmu.name} stopped at t={result.stop_time:g} s")
    values = {name: np.asarray(result[name], dtype=float) for name in names}
    if any(v.shape != stamps.shape or not np.all(np.isfinite(v)) for v in values.values()):
        raise RuntimeError(f"{fmu.name}: no finite trajectory on the stamps")
    return values


# -- drawing ---------------------------------------------------------------------------------------

def log_uniform(rng, low: float, high: float) -> float:
    return float(math.exp(rng.uniform(math.log(low), math.log(high))))


@dataclass
class DataSettings:
    rate: float
    jitter: float
    runs: int
    spread_columns: bool
    noise_model: str
    noise_rho: float
    noise_filter_tau: float
    noise_filter_order: int
    separate_validation: bool

    def bench(self):
        """The synth bench whose unit_noise draws this noise colour."""
        from fmubuilder.synth import BenchSettings
        return BenchSettings(noise_model=self.noise_model, noise_rho=self.noise_rho,
                             noise_filter_tau=self.noise_filter_tau, noise_filter_order=self.noise_filter_order,
                             fine_step=min(0.01, 0.25 / self.rate))


def draw_data_settings(rng) -> DataSettings:
    rate = log_uniform(rng, *RATE_RANGE)
    runs = int(rng.integers(1, 4))
    model = str(rng.choice(["white", "ar1", "lowpass"]))
    return DataSettings(
        rate=rate, jitter=float(rng.uniform(0.0, 0.4)), runs=runs,
        spread_columns=bool(runs >= 2 and rng.random() < 0.5), noise_model=model,
        noise_rho=float(rng.uniform(0.3, 0.9)) if model == "ar1" else 0.0,
        noise_filter_tau=float(rng.uniform(1.0, 3.0) / rate) if model == "lowpass" else 0.0,
        noise_filter_order=int(rng.integers(1, 3)) if model == "lowpass" else 1,
        separate_validation=bool(rng.random() < 0.5))


def effect_variables(info) -> list[str]:
    """What an effect may read: the states, outputs and locals of the FMU that are continuous reals
    (no derivatives: those are what effects change)."""
    derivatives = {d.name for d in info.derivatives}
    return [v.name for v in info.variables.values()
            if v.type == "Real" and v.variability == "continuous" and v.causality in ("output", "local")
            and v.name not in derivatives and v.name != "time"]


def draw_part(rng, family: str, trajectory: dict[str, np.ndarray], readable: list[str]) -> Part:
    """One part, its centres and widths placed inside the training run's range of its variables."""
    count = 2 if family == "product" else 1
    names = [str(n) for n in rng.choice(readable, size=count, replace=False)]
    centers, widths = [], []
    for name in names:
        values = trajectory[name]
        low, high = np.quantile(values, [0.1, 0.9])
        span = max(high - low, 1e-9)
        if family in ("sign", "stribeck"):      # around zero when the variable crosses it
            center = 0.0 if values.min() < 0 < values.max() else float(rng.uniform(low, high))
        elif family == "bump":
            center = float(rng.uniform(low, high))
        else:
            center = float(np.median(values))
        width = {"bump": log_uniform(rng, 0.05, 0.5), "stribeck": log_uniform(rng, 0.1, 0.5),
                 "sign": log_uniform(rng, 0.005, 0.1), "saturation": log_uniform(rng, 0.1, 0.5),
                 "deadzone": log_uniform(rng, 0.1, 0.4), "product": 1.0}[family] * span
        if family == "product":                 # z = v / its typical size
            center, width = 0.0, max(float(np.sqrt(np.mean(values ** 2))), 1e-9)
        centers.append(center)
        widths.append(width)
    sharpness = log_uniform(rng, 2.0, 10.0) if family == "stribeck" else 1.0
    return Part(family, names, centers, widths, 1.0, sharpness)


def draw_effect(rng, base: Base, trajectory: dict[str, np.ndarray], readable: list[str]) -> Effect:
    """Family, channel, variables and amplitude (relative to the channel's own rate of change; the
    noise, not the amplitude, sets the size against the noise)."""
    channel = str(rng.choice(base.channels))
    count = 1 if rng.random() < 0.7 else 2       # sums of two parts
    parts = []
    scale = float(np.sqrt(np.mean(trajectory[channel] ** 2))) or 1.0
    candidates = [n for n in readable if np.ptp(trajectory[n]) > 1e-9]
    # A product needs two variables that move: not on a model with one.
    families = [f for f in FAMILIES if f != "product" or len(candidates) >= 2]
    for _ in range(count):
        family = str(rng.choice(families))
        part = draw_part(rng, family, trajectory, candidates)
        peak = float(np.max(np.abs(part.shape(trajectory)))) or 1.0
        part.amplitude = float(rng.choice([-1, 1])) * log_uniform(rng, 0.05, 0.5) * scale / peak
        parts.append(part)
    return Effect(channel, parts)


# -- the truth -------------------------------------------------------------------------------------

def export_truth(declared: Path, effect: Effect, folder: Path) -> Path:
    from fmubuilder.export import HybridSpec, export_hybrid
    from fmubuilder.fmi import read_model_info
    work = folder / "truth_spec"
    work.mkdir(exist_ok=True)
    spec = HybridSpec(original_fmu=declared, original_guid=read_model_info(declared).guid,
                      channels=[effect.channel], inputs=effect.inputs, onnx=effect.write_onnx(work / "effect.onnx"),
                      p_ann=[1.0], p_fmu=[1.0], term="fitted term", expression=effect.describe())
    spec.save(work / "spec.json")
    return export_hybrid(spec, folder / "truth.fmu", force=True, win64=False)


def check_truth(declared: Path, truth: Path, effect: Effect, times, states, inputs: dict, start_values: dict) -> float:
    """Largest |der_truth - (der_declared + effect)| over the given (time, state) points, relative to
    the channel's scale: the truth FMU adds exactly the effect to exactly its channel."""
    from fmubuilder.fmi.instance import Fmu
    with Fmu(declared) as plain, Fmu(truth) as wrapped:
        got, want = [], []
        for fmu, collect in ((plain, want), (wrapped, got)):
            instance = fmu.instantiate()
            instance.setup_experiment(float(times[0]))
            instance.set(start_values)
            instance.enter_initialization_mode()
            instance.exit_initialization_mode()
            instance.new_discrete_states()
            instance.enter_continuous_time_mode()
            for t, x, u in zip(times, states, inputs_rows(inputs, len(times))):
                instance.set_time(float(t))
                if u:
                    instance.set(u)
                instance.set_continuous_states(x)
                derivatives = dict(zip([d.name for d in fmu.info.derivatives], instance.get_derivatives()))
                read = dict(zip(effect.inputs, instance.get(effect.inputs))) if fmu is plain else {}
                collect.append((derivatives, read))
            instance.terminate()
            instance.free()
    worst, scale = 0.0, 1e-300
    for (der_plain, read), (der_truth, _) in zip(want, got):
        for name, value in der_plain.items():
            expected = value + (float(effect.evaluate({k: np.array(v) for k, v in read.items()})) if name == effect.channel else 0.0)
            worst = max(worst, abs(der_truth[name] - expected))
            scale = max(scale, abs(expected))
    return worst / scale


def inputs_rows(inputs: dict[str, np.ndarray], count: int):
    return [{name: float(values[k]) for name, values in inputs.items()} for k in range(count)]


# -- the case --------------------------------------------------------------------------------------

ROLES = ("train", "validation", "test")


def draw_kind(rng) -> str:
    u = rng.random()
    return "none" if u < NO_EFFECT_SHARE else "parameter" if u < NO_EFFECT_SHARE + PARAMETER_SHARE else "effect"


def draw_head(rng) -> tuple[Base, str, DataSettings]:
    """The first draws of a case: its base model, its kind and how its data are logged."""
    base = BASES[int(rng.integers(len(BASES)))]
    return base, draw_kind(rng), draw_data_settings(rng)


def stamped_run(rng, base: Base, settings: DataSettings) -> tuple[Run, np.ndarray, dict[str, np.ndarray]]:
    """A run's excitation, its logger stamps and its inputs sampled at them."""
    from fmubuilder.synth import sample_times
    run = base.draw_run(rng)
    stamps = sample_times(0.0, run.duration, settings.rate, settings.jitter, 1e-3, rng)
    return run, stamps, {name: signal(stamps) for name, signal in run.inputs.items()}


def build_case(seed: int, folder: Path) -> dict:
    """Draw the case of `seed` and write it into `folder` (created); returns truth.json's content."""
    from fmubuilder.fmi import read_model_info
    rng = np.random.default_rng(seed)
    base, kind, settings = draw_head(rng)
    folder.mkdir(parents=True, exist_ok=True)
    declared = folder / "declared.fmu"
    shutil.copyfile(base.fmu(), declared)
    info = read_model_info(declared)
    runs = {role: stamped_run(rng, base, settings) for role in ROLES
            if role != "validation" or settings.separate_validation}
    readable = effect_variables(info)
    train_run, train_stamps, train_inputs = runs["train"]
    plain_train = simulate_at(declared, train_stamps, readable + base.channels + [s.name for s in info.states],
                              train_run.start_values, train_inputs)
    for _ in range(MAX_ATTEMPTS):
        try:
            truth_fmu, truth_parameters, effect, check, clean = draw_truth(rng, kind, base, info, folder, runs,
                                                                           plain_train, readable)
            break
        except RuntimeError as exc:     # a truth that diverges or equals the declared model: draw again
            print(f"seed {seed}: truth drawn again ({exc})")
    else:
        raise RuntimeError(f"seed {seed}: no usable truth in {MAX_ATTEMPTS} draws")
    noise_std, target = draw_noise(rng, kind, settings, *clean["test"])
    truth = {"seed": seed, "base": base.name, "kind": kind, "signals": base.signals,
             "effect": effect.as_dict() if effect else None,
             "parameters": {name: {"declared": float(info.variable(name).start), "truth": value}
                            for name, value in truth_parameters.items()},
             "truth_check_relative_error": check, "target_ratio": target,
             "noise_std_one_run": noise_std,
             "noise_variance": {s: noise_std[s] ** 2 / settings.runs for s in base.signals},
             "data": settings.__dict__, "files": {}}
    truth["plain_test_ratio"] = {s: float(np.mean((clean["test"][1][s] - clean["test"][0][s]) ** 2))
                                 / truth["noise_variance"][s] for s in base.signals}
    for role, (run, stamps, inputs) in runs.items():
        truth["files"][role] = write_data(folder / f"{role}.csv", rng, settings, stamps, clean[role][0],
                                          noise_std, inputs, run.start_values)
    (folder / "truth.json").write_text(json.dumps(truth, indent=2) + "\n")
    return truth


def draw_truth(rng, kind: str, base: Base, info, folder: Path, runs: dict, plain_train: dict, readable: list):
    """The truth of the case (an effect exported into truth.fmu and checked, or a wrong parameter) and
    the noise-free trajectories (truth, declared) of each role's run."""
    declared = folder / "declared.fmu"
    truth_fmu, truth_parameters, effect, check = declared, {}, None, None
    _, train_stamps, train_inputs = runs["train"]
    if kind == "effect":
        effect = draw_effect(rng, base, plain_train, readable)
        truth_fmu = export_truth(declared, effect, folder)
        every = max(1, len(train_stamps) // CHECK_POINTS)
        states = np.column_stack([plain_train[s.name] for s in info.states])[::every]
        check = check_truth(declared, truth_fmu, effect, train_stamps[::every], states,
                            {k: v[::every] for k, v in train_inputs.items()}, runs["train"][0].start_values)
    elif kind == "parameter":
        name = str(rng.choice(base.parameters))
        factor = log_uniform(rng, 1.05, 1.5) ** float(rng.choice([-1, 1]))
        truth_parameters = {name: float(info.variable(name).start) * factor}
    clean = {role: (simulate_at(truth_fmu, stamps, base.signals, {**run.start_values, **truth_parameters}, inputs),
                    simulate_at(declared, stamps, base.signals, run.start_values, inputs))
             for role, (run, stamps, inputs) in runs.items()}
    if kind != "none" and not any(np.any(t[s] != p[s]) for t, p in clean.values() for s in base.signals):
        raise RuntimeError("the truth equals the declared model")
    return truth_fmu, truth_parameters, effect, check, clean


def draw_noise(rng, kind: str, settings: DataSettings, truth: dict, plain: dict) -> tuple[dict, float | None]:
    """One run's noise sigma per signal: random weights times each signal's spread, scaled so that
    the worst signal's plain test MSE is `target` times its noise variance (no effect: a noise of
    0.1-3 % of the signal's spread)."""
    weights = {s: log_uniform(rng, 0.5, 2.0) * max(float(np.std(v)), 1e-6 * (1 + float(np.max(np.abs(v)))))
               for s, v in truth.items()}
    if kind == "none":
        scale = log_uniform(rng, 1e-3, 3e-2)
        return {s: scale * w for s, w in weights.items()}, None
    target = log_uniform(rng, *RATIO_RANGE)
    worst = max(float(np.mean((plain[s] - truth[s]) ** 2)) * settings.runs / w ** 2 for s, w in weights.items())
    if not worst > 0:
        raise RuntimeError("the truth equals the declared model on the test run")
    scale = math.sqrt(worst / target)
    return {s: scale * w for s, w in weights.items()}, target


def write_data(path: Path, rng, settings: DataSettings, stamps, clean: dict, noise_std: dict,
               inputs: dict, start_values: dict) -> str:
    """The measured CSV (mean over the runs, optional _std columns, input columns exact) and its sidecar."""
    from fmubuilder.synth import format_csv, unit_noise
    bench = settings.bench()
    columns = {"time": stamps}
    spread = {}
    for signal, values in clean.items():
        samples = np.array([values + noise_std[signal] * unit_noise(stamps, bench, rng) for _ in range(settings.runs)])
        columns[signal] = samples.mean(axis=0)
        if settings.spread_columns:
            spread[signal + "_std"] = samples.std(axis=0, ddof=1)
    columns.update(spread)
    columns.update(inputs)
    path.write_text(format_csv(columns, 1e-3))
    sidecar = {"data_file": path.name, "start_values": start_values,
               "bench": {"runs": settings.runs, "lag": 0.0, "sample_rate": settings.rate}}
    path.with_name(path.name + ".json").write_text(json.dumps(sidecar, indent=2) + "\n")
    return path.name


def write_manifest(path: Path, cases: dict[str, dict], budget: int, seed: int = 0) -> Path:
    """The batch manifest: [defaults] and one [[case]] per folder, paths relative to the manifest."""
    lines = ["[defaults]", f"budget = {budget}", f"seed = {seed}", ""]
    for name, truth in cases.items():
        files = truth["files"]
        lines += ["[[case]]", f'name = "{name}"', f'model = "{name}/declared.fmu"',
                  f'train = ["{name}/{files["train"]}"]']
        if "validation" in files:
            lines.append(f'validation = "{name}/{files["validation"]}"')
        lines += [f'test = "{name}/{files["test"]}"', ""]
    path.write_text("\n".join(lines))
    return path
