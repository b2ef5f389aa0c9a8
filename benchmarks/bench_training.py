"""Which NeuralFMU training gets furthest on the same work: warm start, optimizer, batching.

The DC drive with undeclared windage (examples/dc_drive, truth variant dc_drive_truth_windage),
logged by the test bench (`synth`: 10 Hz, sensor lag, noise) on 0-15 s for training and on
20.5-30 s (a start from rest and a run beyond the training's speeds, another noise seed) held out.
An ANN (8 tanh units) on der(speed) reads speed. Each method gets the same work: `--passes`
passes over the training data with gradient through the solver (an Adam epoch is one pass whatever
its batching; an L-BFGS loss evaluation, line search included, is one pass), as the training's
budget of loss evaluations (one per batch), which it spends exactly. Per method: the
held-out MSE of each measured signal relative to the plain FMU's, averaged (below 1: better), the
optimizer steps, the passes used, and the wall time relative to the first method, measured in the
same run, and in seconds. The collocation warm start (warm_start.py) comes before and is counted apart, in
simulations without gradient.

    python benchmarks/bench_training.py [--passes 12]
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from fmubuilder import synth
from fmubuilder.build import example_fmu
from fmubuilder.data import load_data
from fmubuilder.fmi import read_model_info
from fmubuilder.neural.train import train_neural_fmu

SIGNALS = ("speed", "current", "power", "temperature")
NOISE = {"speed": 0.1, "current": 0.02, "power": 1.0, "temperature": 0.02}
TRAIN, TEST = (0.0, 15.0), (20.5, 30.0)

# name -> (elements the training data are cut into, training settings)
METHODS = {
    "Adam, 1 batch of 8 elements": (8, dict(optimizer="adam", learning_rate=1e-2)),
    "Adam, 4 batches of 4 elements": (16, dict(optimizer="adam", batch_size=4, learning_rate=1e-2)),
    "L-BFGS, 1 batch of 8 elements": (8, dict(optimizer="lbfgs")),
}


def measured(folder: Path, window, seed: int) -> Path:
    settings = synth.BenchSettings(seed=seed, signals=SIGNALS, noise_std=NOISE)
    data = synth.measure(example_fmu("dc_drive_truth_windage"), start_time=window[0], stop_time=window[1],
                         settings=settings)
    path = folder / f"windage_{window[0]:g}_{seed}.csv"
    synth.write_measurement(data, path)
    return path


WARM_STARTS = {"none": {}, "collocation": {"warm_start": True}}
COMBINATIONS = [("none", name) for name in METHODS] + [
    ("collocation", "Adam, 1 batch of 8 elements"), ("collocation", "L-BFGS, 1 batch of 8 elements")]


def run(fmu, train, test, passes: int, warm_start: dict, elements: int, settings: dict) -> dict:
    lbfgs = settings["optimizer"] == "lbfgs"
    length = (train.stop - train.start) / elements * (1 - 1e-9)
    batches = elements // settings["batch_size"] if settings.get("batch_size") else 1
    started = time.perf_counter()
    result = train_neural_fmu(fmu, train, targets=["der(speed)"], inputs=["speed"], topology="residual", hidden=[8],
                              budget=passes * batches, step_size=0.002, element_length=length, ccpt_window=0.5,
                              **warm_start, progress=False, test_data=test, **settings)
    seconds = time.perf_counter() - started
    errors = result.metrics["test_errors"]
    ratio = float(np.mean([errors["after"][s]["mse"] / errors["before"][s]["mse"] for s in SIGNALS]))
    evaluations = result.metrics["loss_evaluations"]
    warm = result.metrics["warm_start"]
    warm_simulations = warm["simulations"] if warm else 0
    result.model.close()
    return {"warm_simulations": warm_simulations, "held_out": ratio, "steps": result.metrics["epochs"] * (1 if lbfgs else batches),
            "passes": evaluations / batches, "seconds": seconds,
            "first_loss": result.history[0]["loss"] if result.history else float("nan")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--passes", type=int, default=12, help="passes over the training data per method")
    args = parser.parse_args()
    fmu = example_fmu("dc_drive")
    info = read_model_info(fmu)
    with tempfile.TemporaryDirectory() as folder:
        train = load_data(measured(Path(folder), TRAIN, 0), info)
        test = load_data(measured(Path(folder), TEST, 1), info)
        rows = []
        for warm_start, name in COMBINATIONS:
            elements, settings = METHODS[name]
            rows.append((name, warm_start, run(fmu, train, test, args.passes, WARM_STARTS[warm_start], elements,
                                               settings)))
    baseline = rows[0][2]["seconds"]
    print(f"DC drive windage, {args.passes} passes over 15 s of training data; held out: 20.5-30 s")
    print("| warm start | method | warm-start simulations | first loss | held-out MSE ratio | optimizer steps | "
          "passes | wall time ratio | wall time (s) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, warm_start, r in rows:
        print(f"| {warm_start} | {name} | {r['warm_simulations']} | {r['first_loss']:.3f} | {r['held_out']:.3f} | "
              f"{r['steps']} | {r['passes']:.0f} | {r['seconds'] / baseline:.2f} | {r['seconds']:.1f} |")


if __name__ == "__main__":
    main()
