"""NeuralFMU speed and training: (a) forward simulation of a hybrid VLDM against the plain FMU in the
same engine, (b) the demo's NeuralFMU trained on the VLDM extra-resistance data against the same ANN
fitted to the true effect.

(a) The VLDM over its 1101.42 s CADC training cycle (110,142 time events), explicit Euler with
    h = 0.01 s, in fmubuilder's engine: FmuSystem (plain) against NeuralFmuSystem (an active
    16x16 tanh ANN on der(speed), as after training). Best of --repeats; ratio hybrid / plain
    (target <= 1.5); the two alternate. The differentiable torch solver (no gradient) is timed once,
    and with a gradient (4 elements of 30 s side by side, forward and backward, best of --repeats)
    against the plain FMU's time for as many simulated seconds.
(b) The NeuralFMU candidate as `hybridize` trains it in `fmubuilder demo`: an ANN on der(speed)
    reading the speed, the first 80 % of the CADC road cycle (measured speed, power, energy from
    `fmubuilder synth` of the extra-resistance truth FMU) in 100 s elements, the loss on all three
    signals, the workflow's warm start and optimizer, a budget of --evaluations loss evaluations
    (work, not seconds); with --last-layer S, then the last layer refined over the whole training
    run (S simulations; hybridize does not on several elements). Then the same ANN is fitted,
    without the solver, to the resistance the truth adds (examples/vldm/model.c), and both are
    scored by the training's loss on the same elements: the ratio trained / true-effect shows how much of the data's information the training
    uses (target <= 3). Both end with the paper's table (energy MSE, max and final error, FMU against
    the hybrid, whole training and test cycles, Euler h = 0.01 s, solver steps and events).

(floor) What the data, the ANN's function class and the scoring allow on the same data: the exact
    resistance as a term, its two coefficients fitted on the training part through the simulation,
    and the ANN fitted to the exact resistance, each scored with RK4 (as hybridize scores) and Euler
    (the paper's table) over the whole CADC run and the test run (MSE / noise variance per signal).
    With --hybrid, a VLDM hybrid's ANN against the exact resistance per band of speed, and its ANN
    gate refined through the training part as hybridize refines a fitted term's scale.

(forms) The fitted term's form as `hybridize` chooses it on the same data (hybridize/term_forms.py):
    the diagnosis' term and its leading variables' forms, each fitted through the simulation of the
    training part, scored on the held-out tail (the choice) and on the test run (MSE / noise variance).

(cost) What the training's loss evaluation (all elements side by side, forward and backward, as
    `hybridize` trains: RK4 at h = 0.01 s, the residual ANN on der(speed) reading speed, elements as
    `hybridize` cuts them: at most 100 s, at least recipe.MIN_ELEMENTS; the DC drive's 48 s are one
    element since MIN_ELEMENTS is 1, 7 of 6 s in the cost table of docs/MEASUREMENTS.md, measured before) and a scoring simulation (the plain FMU by the engine,
    RK4 at h = 0.01 s, recorded every step and around events, as `hybridize` scores every model)
    cost on the DC drive (Stribeck data, the 48 s training part) and the VLDM (extra resistance, the
    first --vldm-span seconds of CADC in elements of 100 s), as a ratio against fmpy's plain FMU
    simulation (explicit Euler, h = 0.01 s) over the same span, measured in the same run: the
    ratios compare versions of fmubuilder on a busy machine. Best of --repeats, CPU and wall time.

    python benchmarks/bench_neural.py [--part a|b|floor|forms|cost|all] [--repeats R] [--evaluations N] [--last-layer S]
                                      [--optimizer lbfgs|adam] [--vldm-span S] [--hybrid VLDM_HYBRID.fmu]
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np
import torch

from fmubuilder.build import example_fmu
from fmubuilder.neural import NeuralFMU, TopologyConfig, simulate
from fmubuilder.neural.system import simulate_hybrid
from fmubuilder.simulation import simulate as simulate_plain

VLDM_STOP = 1101.42
STEP = 0.01


def best_of(repeats, function):
    best, value = float("inf"), None
    for _ in range(repeats):
        started = time.perf_counter()
        value = function()
        best = min(best, time.perf_counter() - started)
    return best, value


def forward(repeats: int) -> float:
    path = example_fmu("vldm")
    torch.manual_seed(0)
    model = NeuralFMU(path, TopologyConfig(channels=["der(speed)"], inputs=["speed", "der(speed)"], hidden=[16, 16]),
                      start_values={"cycle": 1})
    with torch.no_grad():
        model.topology.gate_ann.fill_(0.05)  # active: the network runs in every evaluation
    variables = ["speed", "power", "energy"]
    t_plain = t_hybrid = float("inf")
    for _ in range(repeats):  # alternately, so that a change of the machine's load hits both
        t, plain = best_of(1, lambda: simulate_plain(
            path, start_time=0.0, stop_time=VLDM_STOP, start_values={"cycle": 1}, solver="euler", step_size=STEP,
            output_interval=1.0, variables=variables))
        t_plain = min(t_plain, t)
        t, hybrid = best_of(1, lambda: simulate_hybrid(
            model, start_time=0.0, stop_time=VLDM_STOP, variables=variables, solver="euler", step_size=STEP,
            output_interval=1.0))
        t_hybrid = min(t_hybrid, t)
    started = time.perf_counter()
    with torch.no_grad():
        simulate(model, VLDM_STOP, STEP, record=variables)
    t_torch = time.perf_counter() - started
    t_gradient = min(gradient_step(model, variables) for _ in range(repeats))
    stats = plain.stats
    print(f"(a) VLDM forward, 0..{VLDM_STOP} s, Euler h={STEP} s ({stats.steps} steps, {stats.time_events} time "
          f"events, {stats.state_events} state events)")
    print(f"    plain FMU (engine)        {t_plain:7.2f} s")
    print(f"    NeuralFMU (engine, numpy) {t_hybrid:7.2f} s   ratio {t_hybrid / t_plain:.2f}  (target <= 1.5)")
    print(f"    NeuralFMU (torch solver, no grad) {t_torch:7.2f} s   ratio {t_torch / t_plain:.2f}")
    same_time = t_plain * GRADIENT_ELEMENTS * GRADIENT_SPAN / VLDM_STOP   # the plain FMU over as many seconds
    print(f"    NeuralFMU (torch solver, {GRADIENT_ELEMENTS} x {GRADIENT_SPAN:g} s, forward + backward) "
          f"{t_gradient:7.2f} s   ratio {t_gradient / same_time:.2f}")
    print(f"    energy at the end: plain {plain['energy'][-1]:.6g} J, hybrid {hybrid['energy'][-1]:.6g} J")
    model.close()
    return t_hybrid / t_plain


GRADIENT_ELEMENTS, GRADIENT_SPAN = 4, 30.0


def gradient_step(model, variables) -> float:
    """Wall time of one training step's simulation: elements side by side, loss, backward."""
    from fmubuilder.neural.solve import ElementStart
    started = time.perf_counter()
    run = simulate(model, GRADIENT_SPAN, STEP, starts=[ElementStart(0.0)] * GRADIENT_ELEMENTS, record=variables)
    run.signal("energy").pow(2).mean().backward()
    model.zero_grad()
    return time.perf_counter() - started


# The NeuralFMU candidate of the demo (`fmubuilder demo`, the paper's set-up): an ANN on der(speed)
# reading the speed, trained on the first 80 % of the CADC road cycle as `hybridize` trains it.
TARGETS, INPUTS = ["der(speed)"], ["speed"]
# examples/vldm/model.c, VLDM_TRUTH_EXTRA_RESISTANCE: the resistance force the declared model lacks [N].
EXTRA_DRAG_LINEAR, EXTRA_DRAG_QUADRATIC = 1.5, 0.06


def extra_resistance_data():
    """The demo's VLDM extra-resistance data: (FMU, (train csv, test csv), data sets generated first,
    (whole CADC run, its first 80 % as hybridize trains on it, WLTC class 2 test run),
    (train start values, test start values), sensor lag)."""
    from fmubuilder.data import load_data, read_sidecar
    from fmubuilder.examples_zoo import cached_data, vldm_data_sets
    from fmubuilder.fmi import read_model_info
    from fmubuilder.hybridize import workflow

    paths, generated = cached_data([d for d in vldm_data_sets() if d.variant.key == "extra_resistance"])
    train_csv = next(p for p in paths if "_train_" in p.name)
    test_csv = next(p for p in paths if "_test_" in p.name)
    fmu = example_fmu("vldm")
    info = read_model_info(fmu)
    whole, test = load_data(train_csv, info), load_data(test_csv, info)
    split = whole.start + (1.0 - workflow.VALIDATION_SHARE) * (whole.stop - whole.start)
    train = whole.window(whole.start, float(whole.time[np.searchsorted(whole.time, split, side="right") - 1]))
    starts = read_sidecar(train_csv)["start_values"], read_sidecar(test_csv)["start_values"]
    return fmu, (train_csv, test_csv), generated, (whole, train, test), starts, read_sidecar(train_csv)["bench"]["lag"]


def training(evaluations: int, optimizer: str, loss_scale: str, last_layer: int) -> None:
    from fmubuilder.hybridize import recipe
    from fmubuilder.neural.train import train_neural_fmu

    fmu, (train_csv, test_csv), generated, (whole, train, test), (train_start, test_start), lag = extra_resistance_data()
    span = train.stop - train.start
    settings = dict(element_length=min(recipe.MAX_ELEMENT_LENGTH, span / recipe.MIN_ELEMENTS),
                    loss_signals=list(train.names), warm_start=recipe.WARM_START,
                    ccpt_window=recipe.COLLOCATION_WINDOW, optimizer=optimizer, solver="rk4", step_size=STEP,
                    loss_scale=loss_scale, last_layer_simulations=last_layer)
    print(f"(b) training on {train_csv.name} [{train.start:g}, {train.stop:g}] s, testing on {test_csv.name} "
          f"({generated} data set(s) generated first): ANN on {', '.join(TARGETS)} reading {', '.join(INPUTS)}, "
          f"loss on {', '.join(train.names)} (scale: {loss_scale}), {optimizer}, {evaluations} loss evaluations, "
          f"sensor lag {lag} s")
    trainers = []

    def keep_trainer(epoch, trainer):
        trainers[:] = [trainer]
        print(f"    step {epoch:3d}  loss {trainer.history[-1]['loss']:.5f}  "
              f"({trainer.loss_evaluations} evaluations)", flush=True)
        return False

    cpu = time.process_time()
    result = train_neural_fmu(fmu, train, targets=TARGETS, inputs=INPUTS, start_values=train_start,
                              topology="residual", budget=evaluations, progress=False, on_epoch=keep_trainer,
                              **settings)
    cpu = time.process_time() - cpu
    print(f"    trained in {cpu:.1f} s CPU ({os.cpu_count()} cores); warm start: {result.metrics['warm_start']}")
    if last_layer:
        print(f"    last layer refined on the whole training run: {result.metrics['last_layer']}")
    trainer, model = trainers[0], result.model
    trained = trainer.signal_losses()
    trained_state = {k: v.clone() for k, v in model.topology.state_dict().items()}
    fit_error = fit_true_effect(model, train)
    true = trainer.signal_losses()
    print(f"    the same ANN fitted to the true effect (relative fit error {fit_error:.2g}); the training's loss "
          f"on its elements, per signal MSE / {'the plain FMU' if loss_scale == 'plain' else 'the noise variance'}'s, "
          f"and their mean (the loss):")
    print("    | signal | trained | true effect | ratio (target <= 3) |\n    |---|---|---|---|")
    for name, value in [*trained.items(), ("loss", None)]:
        a = value if value is not None else sum(trained.values()) / len(trained)
        b = true[name] if value is not None else sum(true.values()) / len(true)
        print(f"    | {name} | {a:.4g} | {b:.4g} | {a / b:.3g} |")
    data_sets = {"train (CADC road)": (whole, train_start), "test (WLTC class 2)": (test, test_start)}
    paper_table(model, data_sets, lag, "ANN fitted to the true effect")
    model.topology.load_state_dict(trained_state)
    paper_table(model, data_sets, lag, "trained NeuralFMU")
    model.close()


def fit_true_effect(model, train) -> float:
    """Fit the model's ANN, without the solver, to the resistance the declared VLDM lacks, on the
    measured speeds of the training data (the effect is a function of the speed alone, so the
    target is exact at any sample); returns the relative error of the fit."""
    from fmubuilder.neural.warm_start import fit_full_batch, scale_output_to_effect
    linear, quadratic = exact_coefficients(model)
    speed = torch.from_numpy(np.asarray(train.signals["speed"], dtype=float))
    x, target = speed[:, None], (linear * speed + quadratic * speed * speed.abs())[:, None]
    scale_output_to_effect(model.topology, target)
    fit_full_batch(model.topology, x, target, iterations=1000, bounded=False, weight_decay=0.0)
    with torch.no_grad():
        return float(((model.topology.correction(x) - target) ** 2).mean() / (target ** 2).mean())


def exact_coefficients(model) -> tuple[float, float]:
    """The resistance the truth adds as der(speed) += linear * v + quadratic * v|v| (the force over
    the model's mass times its mass factor, from its start values)."""
    mass, factor = (float(model.start_values.get(name, model.info.variable(name).start)) for name in ("mass", "mass_factor"))
    return -EXTRA_DRAG_LINEAR / (mass * factor), -EXTRA_DRAG_QUADRATIC / (mass * factor)


def floor() -> None:
    """(floor) What the data, the function class and the scoring allow, on the demo's data: MSE /
    noise variance per signal, whole CADC run and WLTC class 2 test run, RK4 (as hybridize scores)
    and Euler (the paper's table), h = 0.01 s, through the sensor lag, for the plain FMU, the exact
    resistance as a term c1 v + c2 v|v| on der(speed), those two coefficients fitted again on the
    training part through the simulation (Gauss-Newton, finite differences), and the demo's ANN
    (16x16 tanh on der(speed) reading speed) fitted to the exact resistance without the solver."""
    from fmubuilder.neural.train import data_errors, predicted_at_samples, simulate_over

    fmu, _, _, (whole, train, test), (train_start, test_start), lag = extra_resistance_data()
    runs = {"whole CADC": (whole, train_start), "test WLTC2": (test, test_start)}

    def with_term(coefficients) -> NeuralFMU:
        """The declared model with der(speed) += c1 v + c2 v|v| (a base term, its ANN zero)."""
        terms = [{"variable": "speed", "basis": basis, "center": 0.0, "coefficient": float(c)}
                 for basis, c in zip(("w", "w*|w|"), coefficients)]
        return NeuralFMU(fmu, TopologyConfig(channels=TARGETS, inputs=INPUTS, kind="residual", base_terms=terms),
                         start_values=train_start)

    probe = NeuralFMU(fmu, TopologyConfig(), start_values=train_start)
    exact = np.array(exact_coefficients(probe))
    probe.close()

    def training_residuals(coefficients) -> np.ndarray:
        model = with_term(coefficients)
        run = simulate_over(model, whole, STEP, "rk4", train_start)
        model.close()
        part = whole.time <= train.stop
        return np.concatenate([(predicted_at_samples(whole, run, name, lag) - whole.signals[name])[part]
                               / np.sqrt(whole.noise_variance(name)) for name in whole.signals])

    fitted = exact.copy()
    for _ in range(3):
        base = training_residuals(fitted)
        columns = []
        for j in range(2):
            moved = fitted.copy()
            moved[j] *= 1.01
            columns.append((training_residuals(moved) - base) / (moved[j] - fitted[j]))
        fitted = fitted + np.linalg.lstsq(np.stack(columns, axis=1), -base, rcond=None)[0]
    torch.manual_seed(0)
    ann = NeuralFMU(fmu, TopologyConfig(channels=TARGETS, inputs=INPUTS, kind="residual", hidden=[16, 16]),
                    start_values=train_start)
    speeds = np.asarray(train.signals["speed"], dtype=float)[:, None]
    ann.topology.initialise_scaling(speeds, exact[0] * speeds + exact[1] * speeds * np.abs(speeds))
    fit_error = fit_true_effect(ann, train)
    exact_term = with_term(exact)
    models = {"plain FMU": (exact_term, True), "exact resistance (term)": (exact_term, False),
              f"term fitted on the training part (coefficients x{fitted[0] / exact[0]:.5f}, x{fitted[1] / exact[1]:.5f})":
                  (with_term(fitted), False),
              f"16x16 tanh ANN fitted to the exact resistance (relative error {fit_error:.2g})": (ann, False)}
    names = list(whole.signals)
    print("(floor) MSE / noise variance per signal (" + ", ".join(names) + ")")
    print("| model | data | RK4 | Euler |\n|---|---|---|---|")
    for label, (model, plain) in models.items():
        for data_label, (data, start) in runs.items():
            cells = []
            for solver in ("rk4", "euler"):
                errors = data_errors(data, simulate_over(model, data, STEP, solver, start, plain=plain), lag)
                cells.append(", ".join(f"{errors[n]['mse'] / data.noise_variance(n):.3g}" for n in names))
            print(f"| {label} | {data_label} | {cells[0]} | {cells[1]} |", flush=True)
    for model in {id(m): m for m, _ in models.values()}.values():
        model.close()


def term_forms() -> None:
    """(forms) The fitted term's form as `hybridize` chooses it (hybridize/term_forms.py), no truth: the
    diagnosis of the training part, then its term and its leading variables' forms, each fitted
    through the simulation of the training part, scored on the held-out tail (the score that
    chooses) and, here only, on the test run; MSE / noise variance per signal."""
    import math

    from fmubuilder.diagnose import diagnose
    from fmubuilder.hybridize.choice import noise_margin
    from fmubuilder.hybridize.evaluate import Scoring
    from fmubuilder.hybridize.term_forms import candidate_forms, choose_form, fit_forms
    from fmubuilder.hybridize.workflow import Part
    from fmubuilder.neural.train import data_errors, simulate_over

    fmu, _, _, (whole, train, test), (train_start, test_start), lag = extra_resistance_data()
    diagnosis = diagnose(fmu, train, train_start)
    train_start = {**train_start, **diagnosis.start_values}
    tail = Part(whole, train_start, (float(whole.time[whole.time > train.stop][0]), whole.stop))
    noise = {e.signal: e.noise for e in diagnosis.errors}
    forms = candidate_forms(diagnosis)
    cpu = time.process_time()
    fits = fit_forms(fmu, diagnosis.channel, forms, [(train, train_start)], [tail], Scoring("rk4", STEP), noise, {},
                     show=False)
    cpu = time.process_time() - cpu
    margin = noise_margin([tail.samples().time], len(train.names))
    chosen = choose_form(fits, margin)
    names = list(train.names)
    print(f"(forms) the diagnosis' term: {diagnosis.fitted_term['expression']}; MSE / noise variance "
          f"({', '.join(names)}), RK4 h = {STEP} s; margin x{margin:.3g}; the forms' fits and validation "
          f"{cpu:.0f} s CPU")
    print("| form | coefficients (x the start) | simulations | training part | held-out tail | validation score "
          "| test WLTC2 | chosen |\n|---|---|---|---|---|---|---|---|")
    for fit in fits:
        model = NeuralFMU(fmu, TopologyConfig(channels=[diagnosis.channel], kind="residual",
                                              inputs=list(dict.fromkeys(t["variable"] for t in fit.terms)),
                                              base_terms=fit.terms), start_values=train_start)
        cells = []
        for data, run_data, start in ((train, train, train_start), (tail.samples(), whole, train_start),
                                      (test, test, test_start)):
            errors = data_errors(data, simulate_over(model, run_data, STEP, "rk4", start), lag)
            cells.append(", ".join(f"{errors[n]['mse'] / data.noise_variance(n):.3g}" for n in names))
        model.close()
        moved = ", ".join(f"{t['coefficient']:.4g} (x{t['coefficient'] / c:.3g})" for t, c in zip(fit.terms, fit.start))
        score = f"{fit.validation_score:.3g}" if math.isfinite(fit.validation_score) else "does not simulate"
        print(f"| {fit.label} | {moved} | {fit.simulations} | {cells[0]} | {cells[1]} | {score} | {cells[2]} | "
              f"{'**yes**' if fit is chosen else 'no'} |", flush=True)


SPEED_BANDS = (0.5, 2.0, 5.0, 8.0, 11.0, 14.0, 17.0, 20.0, 23.0, 26.0, 29.0)


def hybrid_against_truth(hybrid_fmu: str) -> None:
    """(floor --hybrid) A VLDM hybrid whose ANN on der(speed) reads the speed (`fmubuilder demo`'s
    NeuralFMU): its network (the ONNX in the FMU, by onnxruntime) against the exact resistance, the
    mean ratio over bands of speed, beside each run's share of the resistance's energy |F v| dt in
    the band; then its ANN gate refined as hybridize refines a fitted term's scale, through the
    simulation of the training part, and the hybrid scored with the gate at 1 and refined (RK4)."""
    import math
    import tempfile
    from pathlib import Path

    from fmubuilder.export.network import OnnxNetwork
    from fmubuilder.export.validate import _embedded_spec
    from fmubuilder.hybridize.evaluate import Scoring, evaluate
    from fmubuilder.hybridize.refine_term import refine_scales

    fmu, _, _, (whole, train, test), (train_start, test_start), _ = extra_resistance_data()
    probe = NeuralFMU(fmu, TopologyConfig(), start_values=train_start)
    linear, quadratic = exact_coefficients(probe)
    probe.close()
    with tempfile.TemporaryDirectory() as folder:
        spec, gates = _embedded_spec(Path(hybrid_fmu), Path(folder))
        if spec.channels != TARGETS or spec.inputs != INPUTS:
            raise SystemExit(f"{hybrid_fmu}: its ANN corrects {spec.channels} reading {spec.inputs}; "
                             f"give a hybrid whose ANN corrects {TARGETS} reading {INPUTS}")
        network = OnnxNetwork(spec.onnx)
        gate = next(name for name, (_, kind) in gates.items() if kind == "p_ann")

        def energy_share(data, low, high):
            speed = np.asarray(data.signals["speed"], dtype=float)
            power = np.abs((linear * speed + quadratic * speed * np.abs(speed)) * speed)
            return power[(speed >= low) & (speed < high)].sum() / power.sum()

        print(f"\n(floor) {hybrid_fmu}: its ANN against the exact resistance, per band of speed")
        print("| speed [m/s] | ANN / truth | share of the training part's resistance energy | test's |\n|---|---|---|---|")
        for low, high in zip(SPEED_BANDS[:-1], SPEED_BANDS[1:]):
            speeds = np.linspace(low, high, 20)
            ann = np.array([network(np.array([v]))[0] for v in speeds])
            ratio = np.mean(ann / (linear * speeds + quadratic * speeds * speeds))
            print(f"| {low:g}-{high:g} | {ratio:.3f} | {energy_share(train, low, high):.3f} | "
                  f"{energy_share(test, low, high):.3f} |", flush=True)
    scoring = Scoring("rk4", STEP)
    noise = {name: math.sqrt(train.noise_variance(name)) for name in train.names}
    refined = refine_scales(hybrid_fmu, [gate], [(train, train_start)], noise, STEP, show=False)
    print(f"\n{gate} refined through the training part: {refined.to_dict()}")
    print("| gate | training part | test WLTC2 |\n|---|---|---|")
    for scale in (1.0, refined.scales[0]):
        cells = []
        for data, start in ((train, train_start), (test, test_start)):
            errors = evaluate(Path(hybrid_fmu), data, {**start, gate: scale}, scoring).errors
            cells.append(", ".join(f"{errors[n]['mse'] / data.noise_variance(n):.3g}" for n in data.names))
        print(f"| {scale:.6g} | {cells[0]} | {cells[1]} |", flush=True)


def paper_table(model, data_sets: dict, lag: float, title: str) -> None:
    """The paper's table: errors of the cumulative energy, plain FMU against the NeuralFMU, each
    simulated over the whole cycle with the engine (Euler, h = 0.01 s), with its step and event counts."""
    print(f"\n{title}:")
    from fmubuilder.neural.train import data_errors, simulate_over
    step = 0.01
    print("\n| data | model | energy MSE [J²] | max error [J] | final error [J] | MSE factor | steps | time events | state events |")
    print("|---|---|---|---|---|---|---|---|---|")
    for label, (data, start) in data_sets.items():
        rows = {}
        for name, plain in (("FMU", True), ("NeuralFMU", False)):
            run = simulate_over(model, data, step, "euler", start, plain=plain)
            rows[name] = data_errors(data, run, lag)["energy"], run.stats
        before = rows["FMU"][0]["mse"]
        for name, (errors, stats) in rows.items():
            print(f"| {label} | {name} | {errors['mse']:.4g} | {errors['max_abs']:.4g} | {errors['final']:.4g} | "
                  f"{before / errors['mse']:.1f} | {stats.steps} | {stats.time_events} | {stats.state_events} |")


COST_CASES = (("dc_drive", "stribeck"), ("vldm", "extra_resistance"))


def best_clocks(repeats: int, function) -> tuple[float, float]:
    """(CPU seconds, wall seconds) of `function`, each the best of `repeats` calls."""
    cpu = wall = float("inf")
    for _ in range(repeats):
        cpu_started, wall_started = time.process_time(), time.perf_counter()
        function()
        cpu, wall = min(cpu, time.process_time() - cpu_started), min(wall, time.perf_counter() - wall_started)
    return cpu, wall


def cost(repeats: int, vldm_span: float) -> None:
    import fmpy
    from fmubuilder.data import read_sidecar
    from fmubuilder.examples_zoo import cached_data, example_data_sets
    from fmubuilder.fmi import read_model_info
    from fmubuilder.hybridize import recipe, workflow
    from fmubuilder.hybridize.evaluate import Scoring, evaluate, read_data
    from fmubuilder.neural.train import Trainer, TrainSettings

    print(f"(cost) a loss evaluation and a scoring simulation against fmpy's Euler over the same span "
          f"(best of {repeats}; CPU / wall seconds)")
    print("| model | span [s] | elements | fmpy Euler | loss evaluation | ratio | scoring (RK4) | ratio |")
    print("|---|---|---|---|---|---|---|---|")
    for example, variant in COST_CASES:
        sets = [s for s in example_data_sets(example) if s.variant.key == variant]
        paths, _ = cached_data(sets)
        train_csv = next(path for s, path in zip(sets, paths) if s.cycle.role == "train")
        fmu = example_fmu(example)
        whole = read_data(train_csv, read_model_info(fmu))
        stop = whole.start + (1.0 - workflow.VALIDATION_SHARE) * (whole.stop - whole.start)
        if example == "vldm":
            stop = min(stop, whole.start + vldm_span)
        data = whole.window(whole.start, float(whole.time[np.searchsorted(whole.time, stop, side="right") - 1]))
        start_values = read_sidecar(train_csv)["start_values"]
        span = data.stop - data.start

        def plain_fmpy():
            fmpy.simulate_fmu(str(fmu), start_time=data.start, stop_time=data.stop, solver="Euler", step_size=STEP,
                              output_interval=STEP, start_values=start_values, output=list(data.names))

        element_length = min(recipe.MAX_ELEMENT_LENGTH, (whole.stop - whole.start) * (1.0 - workflow.VALIDATION_SHARE)
                             / recipe.MIN_ELEMENTS)
        settings = TrainSettings(element_length=element_length, solver="rk4", step_size=STEP, optimizer="lbfgs",
                                 progress=False, sensor_lag=data.sensor_lag)
        torch.manual_seed(0)
        model = NeuralFMU(fmu, TopologyConfig(channels=TARGETS, inputs=INPUTS, hidden=[16, 16], kind="residual"),
                          start_values)
        trainer = Trainer(model, data, settings, time.perf_counter())
        trainer.prepare()

        def loss_evaluation():
            trainer.batch_loss(trainer.elements, carry=False).backward()
            model.zero_grad()

        t_fmpy = best_clocks(max(repeats, 5), plain_fmpy)    # the baseline is short: more repeats
        t_loss = best_clocks(repeats, loss_evaluation)
        t_score = best_clocks(repeats, lambda: evaluate(fmu, data, start_values, Scoring("rk4", STEP)))
        model.close()
        print(f"| {example} | {span:.0f} | {len(trainer.elements)} | {t_fmpy[0]:.2f} / {t_fmpy[1]:.2f} | "
              f"{t_loss[0]:.2f} / {t_loss[1]:.2f} | {t_loss[0] / t_fmpy[0]:.2f} / {t_loss[1] / t_fmpy[1]:.2f} | "
              f"{t_score[0]:.2f} / {t_score[1]:.2f} | {t_score[0] / t_fmpy[0]:.2f} / {t_score[1] / t_fmpy[1]:.2f} |",
              flush=True)


def main() -> None:
    from fmubuilder.hybridize import recipe
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=["a", "b", "floor", "forms", "cost", "all"], default="all")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--evaluations", type=int, default=10, help="the training's budget of loss evaluations")
    parser.add_argument("--optimizer", choices=["lbfgs", "adam"], default="lbfgs")
    parser.add_argument("--loss-scale", choices=["plain", "noise"], default=recipe.LOSS_SCALE,
                        help="each signal's MSE in the loss divided by the plain FMU's or by its noise variance "
                             "(default: hybridize's)")
    parser.add_argument("--last-layer", type=int, default=0,
                        help="after the training, at most this many simulations of the whole training run refining "
                             "the ANN's last layer (neural/last_layer.py; default 0: none, as hybridize on several elements)")
    parser.add_argument("--hybrid", help="with --part floor: also this VLDM hybrid's ANN against the exact resistance "
                                         "(e.g. fmubuilder demo's vldm_hybrid.fmu when it ships the NeuralFMU)")
    parser.add_argument("--vldm-span", type=float, default=200.0,
                        help="seconds of the VLDM's training data in the cost part (elements of 100 s)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.part in ("a", "all"):
        forward(args.repeats)
    if args.part in ("b", "all"):
        training(args.evaluations, args.optimizer, args.loss_scale, args.last_layer)
    if args.part in ("floor", "all"):
        floor()
        if args.hybrid:
            hybrid_against_truth(args.hybrid)
    if args.part in ("forms", "all"):
        term_forms()
    if args.part in ("cost", "all"):
        cost(args.repeats, args.vldm_span)


if __name__ == "__main__":
    main()
