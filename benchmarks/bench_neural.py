"""NeuralFMU speed: (a) forward simulation of a hybrid VLDM against the plain FMU in the same engine,
(b) training wall time on the VLDM extra-resistance truth data until the held-out energy error falls.

(a) The VLDM over its 1101.42 s CADC training cycle (110,142 time events), explicit Euler with
    h = 0.01 s, in fmubuilder's engine: FmuSystem (plain) against NeuralFmuSystem (an active
    16x16 tanh ANN on der(speed), as after training). Best of --repeats; ratio hybrid / plain
    (target <= 1.5); the two alternate. The differentiable torch solver (no gradient) is timed once.
(b) Train on the CADC road cycle (measured speed, power, energy from `fmubuilder synth` of the
    extra-resistance truth FMU) in 100 s elements, test on WLTC class 2. After every epoch the
    hybrid simulates the test cycle; the run stops when the test MSE of the cumulative energy is
    16 times below the plain FMU's (target: <= 10 min wall time on 2 cores). The test evaluations
    are reported separately from the training time.

    python benchmarks/bench_neural.py [--part a|b|all] [--repeats R] [--budget SECONDS]
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
    stats = plain.stats
    print(f"(a) VLDM forward, 0..{VLDM_STOP} s, Euler h={STEP} s ({stats.steps} steps, {stats.time_events} time "
          f"events, {stats.state_events} state events)")
    print(f"    plain FMU (engine)        {t_plain:7.2f} s")
    print(f"    NeuralFMU (engine, numpy) {t_hybrid:7.2f} s   ratio {t_hybrid / t_plain:.2f}  (target <= 1.5)")
    print(f"    NeuralFMU (torch solver, no grad) {t_torch:7.2f} s   ratio {t_torch / t_plain:.2f}")
    print(f"    energy at the end: plain {plain['energy'][-1]:.6g} J, hybrid {hybrid['energy'][-1]:.6g} J")
    model.close()
    return t_hybrid / t_plain


def training(budget: float) -> float | None:
    from fmubuilder.examples_zoo import cached_data, vldm_data_sets
    from fmubuilder.neural.data import load_data
    from fmubuilder.neural.train import evaluate, train_neural_fmu
    from fmubuilder.synth import read_sidecar

    sets = [d for d in vldm_data_sets() if d.variant.key == "extra_resistance"]
    paths, generated = cached_data(sets)
    train_csv = next(p for p in paths if "_train_" in p.name)
    test_csv = next(p for p in paths if "_test_" in p.name)
    fmu = example_fmu("vldm")
    info_model = NeuralFMU(fmu, TopologyConfig())
    test = load_data(test_csv, info_model.info)
    info_model.close()
    test_start = read_sidecar(test_csv)["start_values"]
    train_start = read_sidecar(train_csv)["start_values"]
    print(f"(b) training on {train_csv.name}, testing on {test_csv.name} ({generated} data set(s) generated first)")

    state = {"evaluation": 0.0, "reached": None, "before": None, "log": []}
    started = time.perf_counter()

    def on_epoch(epoch, trainer):
        t0 = time.perf_counter()
        if state["before"] is None:
            state["before"] = evaluate(trainer.model, test, trainer.step, start_values=test_start, plain=True)["energy"]["mse"]
        after = evaluate(trainer.model, test, trainer.step, start_values=test_start)["energy"]["mse"]
        state["evaluation"] += time.perf_counter() - t0
        factor = state["before"] / after
        wall = time.perf_counter() - started
        training_time = wall - state["evaluation"]
        state["log"].append((epoch, trainer.history[-1]["loss"], factor, training_time))
        print(f"    epoch {epoch:3d}  loss {trainer.history[-1]['loss']:.5f}  test energy MSE factor {factor:7.2f}  "
              f"training {training_time:6.1f} s  (+ test evaluations {state['evaluation']:.1f} s)")
        if factor >= TARGET_FACTOR:
            state["reached"] = training_time
            return True
        return False

    cpu = time.process_time()
    result = train_neural_fmu(fmu, train_csv, targets=["der(speed)"], inputs=["speed"], start_values=train_start,
                              topology="residual", hidden=[16, 16], epochs=200, element_length=100.0,
                              learning_rate=3e-3, decay=0.95, time_budget=budget, progress=False, on_epoch=on_epoch)
    cpu = time.process_time() - cpu
    total = time.perf_counter() - started
    if state["reached"] is None:
        print(f"    target factor {TARGET_FACTOR} NOT reached within {budget:.0f} s")
    else:
        print(f"    reached test energy MSE factor >= {TARGET_FACTOR} after {state['log'][-1][0]} epoch(s): "
              f"{state['reached']:.1f} s wall time for training (target <= 600 s on 2 cores)")
    print(f"    whole run {total:.1f} s wall ({cpu:.1f} s CPU, {os.cpu_count()} cores), of which test "
          f"evaluations {state['evaluation']:.1f} s; training-data energy MSE "
          f"{result.metrics['errors']['before']['energy']['mse']:.4g} -> {result.metrics['errors']['after']['energy']['mse']:.4g}")
    result.model.close()
    return state["reached"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=["a", "b", "all"], default="all")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--budget", type=float, default=900.0, help="time budget of the training run (s)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.part in ("a", "all"):
        forward(args.repeats)
    if args.part in ("b", "all"):
        training(args.budget)


if __name__ == "__main__":
    main()
