"""What one step of the training's simulation costs, against the same step without gradient.

The demo's NeuralFMU (16x16 tanh on der(speed) reading speed, the VLDM, RK4 at h = 0.01 s) over
--span seconds of the CADC training run from its start, one element: the engine's simulation
without gradient (what scoring, the fitted term's forms and the last layer's refinement run), and a
loss evaluation as `hybridize` trains (the batched solver with the FMU as an autograd function,
forward, then backward), each per 0.01 s step (one controller tick, one time event), best of
--repeats. Also the autograd graph's nodes per step, the backward's unit of work. The ratios say
how far the gradient pass is from the simulation that needs none.

    python benchmarks/bench_step_cost.py [--span 20] [--repeats 3]
"""
from __future__ import annotations

import argparse
import time
from collections import Counter

import numpy as np
import torch

from fmubuilder.build import example_fmu
from fmubuilder.data import read_sidecar
from fmubuilder.examples_zoo import cached_data, example_data_sets
from fmubuilder.fmi import read_model_info
from fmubuilder.hybridize.evaluate import read_data
from fmubuilder.neural import NeuralFMU, TopologyConfig
from fmubuilder.neural.train import Trainer, TrainSettings, simulate_over

STEP = 0.01


def graph_nodes(loss: torch.Tensor) -> Counter:
    """The autograd nodes behind `loss`, counted by kind."""
    seen, kinds, stack = set(), Counter(), [loss.grad_fn]
    while stack:
        node = stack.pop()
        if node is None or node in seen:
            continue
        seen.add(node)
        kinds[type(node).__name__] += 1
        stack.extend(next_node for next_node, _ in node.next_functions)
    return kinds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--span", type=float, default=20.0, help="seconds of the training run from its start")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    sets = [s for s in example_data_sets("vldm") if s.variant.key == "extra_resistance"]
    paths, _ = cached_data(sets)
    train_csv = next(path for s, path in zip(sets, paths) if s.cycle.role == "train")
    fmu = example_fmu("vldm")
    whole = read_data(train_csv, read_model_info(fmu))
    stop = float(whole.time[np.searchsorted(whole.time, whole.start + args.span, side="right") - 1])
    data = whole.window(whole.start, stop)
    settings = TrainSettings(element_length=args.span, solver="rk4", step_size=STEP, optimizer="lbfgs",
                             progress=False, sensor_lag=data.sensor_lag)
    torch.manual_seed(0)
    torch.set_num_threads(settings.threads)
    model = NeuralFMU(fmu, TopologyConfig(channels=["der(speed)"], inputs=["speed"], hidden=[16, 16],
                                          kind="residual"), read_sidecar(train_csv)["start_values"])
    trainer = Trainer(model, data, settings, time.perf_counter())
    trainer.prepare()
    steps = (data.stop - data.start) / STEP
    engine = forward = backward = float("inf")
    for _ in range(args.repeats):
        started = time.perf_counter()
        simulate_over(model, data, STEP, "rk4")
        engine = min(engine, time.perf_counter() - started)
        started = time.perf_counter()
        loss = trainer.batch_loss(trainer.elements, carry=False)
        forward = min(forward, time.perf_counter() - started)
        started = time.perf_counter()
        loss.backward()
        backward = min(backward, time.perf_counter() - started)
        model.zero_grad()
    nodes = graph_nodes(trainer.batch_loss(trainer.elements, carry=False))
    model.close()
    per_step = 1e6 / steps
    print(f"VLDM, {data.stop - data.start:.0f} s from the start of the CADC run, {steps:.0f} steps of {STEP} s, "
          f"best of {args.repeats} (wall time per step)")
    print("| what | us per step | ratio to the engine |\n|---|---|---|")
    for label, seconds in (("engine, no gradient (NeuralFMU, RK4)", engine), ("loss evaluation: forward", forward),
                           ("loss evaluation: backward", backward),
                           ("loss evaluation: forward and backward", forward + backward)):
        print(f"| {label} | {seconds * per_step:.0f} | {seconds / engine:.1f} |")
    total = sum(nodes.values())
    common = ", ".join(f"{kind} {count / steps:.1f}" for kind, count in nodes.most_common(6))
    print(f"\nautograd nodes per step: {total / steps:.1f} ({common}, ...); "
          f"backward per node: {backward / total * 1e6:.1f} us")


if __name__ == "__main__":
    main()
