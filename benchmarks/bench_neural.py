"""NeuralFMU speed: (a) forward simulation of a hybrid VLDM against the plain FMU in the same engine,
(b) training wall time on the VLDM extra-resistance truth data until the held-out energy error falls.

(a) The VLDM over its 1101.42 s CADC training cycle (110,142 time events), explicit Euler with
    h = 0.01 s, in fmubuilder's engine: FmuSystem (plain) against NeuralFmuSystem (an active
    16x16 tanh ANN on der(speed), as after training). Best of --repeats; ratio hybrid / plain
    (target <= 1.5); the two alternate. The differentiable torch solver (no gradient) is timed once,
    and with a gradient (4 elements of 30 s side by side, forward and backward, best of --repeats)
    against the plain FMU's time for as many simulated seconds.
(b) Train on the CADC road cycle (measured speed, power, energy from `fmubuilder synth` of the
    extra-resistance truth FMU) in 100 s elements, test on WLTC class 2. Until the test MSE of the
    cumulative energy is 16 times below the plain FMU's, the hybrid simulates the test cycle after
    every epoch: the training wall time to that point (target <= 10 min on 2 cores) excludes these
    evaluations. The run goes on for --epochs and ends with the paper's table (energy MSE, max and
    final error, FMU against NeuralFMU, training and test cycle, solver steps and events).

    python benchmarks/bench_neural.py [--part a|b|all] [--repeats R] [--budget SECONDS] [--epochs N]
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
TARGET_FACTOR = 16.0


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


# The paper's set-up: ANN on der(speed) reading the speed, 100 s elements of the CADC road cycle.
TRAINING = dict(targets=["der(speed)"], inputs=["speed"], topology="residual", hidden=[16, 16],
                element_length=100.0, learning_rate=3e-3, decay=0.95, loss_signals=["energy"])


def training(budget: float, epochs: int) -> None:
    from fmubuilder.examples_zoo import cached_data, vldm_data_sets
    from fmubuilder.data import load_data
    from fmubuilder.neural.train import evaluate, train_neural_fmu
    from fmubuilder.data import read_sidecar

    sets = [d for d in vldm_data_sets() if d.variant.key == "extra_resistance"]
    paths, generated = cached_data(sets)
    train_csv = next(p for p in paths if "_train_" in p.name)
    test_csv = next(p for p in paths if "_test_" in p.name)
    fmu = example_fmu("vldm")
    info_model = NeuralFMU(fmu, TopologyConfig())
    train, test = load_data(train_csv, info_model.info), load_data(test_csv, info_model.info)
    info_model.close()
    train_start, test_start = read_sidecar(train_csv)["start_values"], read_sidecar(test_csv)["start_values"]
    lag = read_sidecar(train_csv)["bench"]["lag"]
    print(f"(b) training on {train_csv.name}, testing on {test_csv.name} ({generated} data set(s) generated first); "
          f"loss on {', '.join(TRAINING['loss_signals'])}, sensor lag {lag} s")

    state = {"evaluation": 0.0, "reached": None, "before": None}
    started = time.perf_counter()

    def on_epoch(epoch, trainer):
        history = trainer.history[-1]
        line = f"    epoch {epoch:3d}  loss {history['loss']:.5f}  lr {history['lr']:.2e}" + \
               ("  (rewound)" if history["backtracked"] else "")
        if state["reached"] is None:  # until the target: the held-out error after every epoch
            t0 = time.perf_counter()
            if state["before"] is None:
                state["before"] = evaluate(trainer.model, test, trainer.step, start_values=test_start, plain=True,
                                           sensor_lag=lag)["energy"]["mse"]
            after = evaluate(trainer.model, test, trainer.step, start_values=test_start, sensor_lag=lag)["energy"]["mse"]
            state["evaluation"] += time.perf_counter() - t0
            factor = state["before"] / after
            line += f"  test energy MSE factor {factor:8.2f}"
            if factor >= TARGET_FACTOR:
                state["reached"] = (epoch, time.perf_counter() - started - state["evaluation"])
        print(line + f"  training {time.perf_counter() - started - state['evaluation']:6.1f} s", flush=True)
        return False

    cpu = time.process_time()
    result = train_neural_fmu(fmu, train_csv, start_values=train_start, epochs=epochs, time_budget=budget,
                              progress=False, on_epoch=on_epoch, **TRAINING)
    cpu = time.process_time() - cpu
    total = time.perf_counter() - started
    if state["reached"] is None:
        print(f"    test energy MSE factor {TARGET_FACTOR} NOT reached")
    else:
        print(f"    test energy MSE factor >= {TARGET_FACTOR} after epoch {state['reached'][0]}: "
              f"{state['reached'][1]:.1f} s wall time of training (target <= 600 s on 2 cores)")
    print(f"    whole run {total:.1f} s wall ({cpu:.1f} s CPU, {os.cpu_count()} cores, {result.metrics['epochs']} "
          f"epochs), of which test evaluations {state['evaluation']:.1f} s; kept the parameters of the lowest loss")
    paper_table(result.model, {"train (CADC road)": (train, train_start), "test (WLTC class 2)": (test, test_start)},
                lag)
    result.model.close()


def paper_table(model, data_sets: dict, lag: float) -> None:
    """The paper's table: errors of the cumulative energy, plain FMU against the NeuralFMU, each
    simulated over the whole cycle with the engine (Euler, h = 0.01 s), with its step and event counts."""
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=["a", "b", "all"], default="all")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--budget", type=float, default=900.0, help="time budget of the training run (s)")
    parser.add_argument("--epochs", type=int, default=20, help="epochs of the training run")
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.part in ("a", "all"):
        forward(args.repeats)
    if args.part in ("b", "all"):
        training(args.budget, args.epochs)


if __name__ == "__main__":
    main()
