"""The training's runs without gradient: the compiled core against the torch batch solver and the floor.

The demo's NeuralFMU (16 x 16 tanh on der(speed) reading the speed, residual, random weights) on
the VLDM over --stop seconds of the CADC cycle (RK4 at h = 0.01 s, a time event every step, the
driver's state events): what the training does without gradient, two ways, best of --repeats,
alternately, against the floor (benchmarks/plain_fmu_loop.c, RK4 over the same span):

  capture   one run over the whole span, the FMU state saved at the starts of --elements elements
            (Trainer._capture_starts)
  elements  the elements side by side from those starts, each --stop / --elements seconds
            (Trainer._all_residuals)

by the torch solver (neural/solve.simulate) and by the core (core_gradient.simulate_without_gradient),
with the largest difference between the two runs' records relative to the records' range.

    python benchmarks/bench_forward_core.py [--stop 881] [--elements 9] [--repeats 3]
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch

from bench_core import build_floor, run_floor
from fmubuilder.build import example_fmu
from fmubuilder.fmi import Fmu
from fmubuilder.neural import NeuralFMU, TopologyConfig
from fmubuilder.neural.core_gradient import simulate_without_gradient
from fmubuilder.neural.solve import ElementStart, simulate

STEP = 0.01
RECORDED = ["speed", "power", "energy", "der(speed)"]


def demo_network() -> NeuralFMU:
    torch.manual_seed(0)
    model = NeuralFMU(example_fmu("vldm"), TopologyConfig(channels=["der(speed)"], inputs=["speed"], hidden=[16, 16]))
    with torch.no_grad():
        for parameter in model.topology.ann.parameters():
            parameter.add_(0.1 * torch.randn_like(parameter))
    return model


def timed(function):
    started = time.perf_counter()
    result = function()
    return time.perf_counter() - started, result


def both_ways(model: NeuralFMU, stop: float, elements: int) -> dict:
    """{(what, how): (seconds, trajectory)} for one repeat."""
    length = round(stop / elements / STEP)
    capture = [k * length for k in range(elements)]
    out = {}
    with torch.no_grad():
        for how, run in (("torch", simulate), ("core", simulate_without_gradient)):
            out["capture", how] = timed(lambda: run(model, stop, STEP, starts=[ElementStart(0.0)], record=RECORDED,
                                                    solver="rk4", capture=capture))
            starts = [out["capture", how][1].captured[k][0] for k in capture]
            out["elements", how] = timed(lambda: run(model, length * STEP, STEP, starts=starts, record=RECORDED,
                                                     solver="rk4"))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stop", type=float, default=881.0)
    parser.add_argument("--elements", type=int, default=9)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)
    model = demo_network()
    best, floor = {}, []
    with tempfile.TemporaryDirectory() as folder, Fmu(model.fmu_path) as fmu:
        program = build_floor(Path(folder))
        names = [v.name for v in fmu.info.states]
        for _ in range(args.repeats):
            floor.append(run_floor(program, fmu, names, args.stop, STEP)[0])
            runs = both_ways(model, args.stop, args.elements)
            for key, (seconds, trajectory) in runs.items():
                best[key] = min(best.get(key, (float("inf"),))[0], seconds), trajectory
    steps = round(args.stop / STEP)
    print(f"VLDM NeuralFMU (16 x 16 tanh on der(speed)), {args.stop:g} s, {steps} RK4 steps of {STEP} s, "
          f"{args.elements} elements; best of {args.repeats}")
    print("| run without gradient | torch solver [s] | core [s] | torch / core | core / floor |\n|---|---|---|---|---|")
    for what in ("capture", "elements"):
        torch_s, core_s = best[what, "torch"][0], best[what, "core"][0]
        print(f"| {what} | {torch_s:.2f} | {core_s:.3f} | {torch_s / core_s:.0f} | {core_s / min(floor):.1f} |")
    print(f"floor (plain C loop, RK4, {args.stop:g} s): {min(floor):.3f} s")
    for what in ("capture", "elements"):
        a, b = best[what, "torch"][1].values, best[what, "core"][1].values
        spread = (a.amax(dim=(0, 1)) - a.amin(dim=(0, 1))).clamp_min(1e-300)
        worst = float(((a - b).abs().amax(dim=(0, 1)) / spread).max())
        print(f"{what}: largest |core - torch| / range over the records: {worst:.1e}")
    model.close()


if __name__ == "__main__":
    main()
