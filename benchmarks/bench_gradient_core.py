"""One loss evaluation with its gradient: the compiled core's forward sensitivities against the
torch batch solver and against the floor, a plain C loop over the same FMU binary.

Two cases, each a NeuralFMU with the training's loss over --span seconds of its training data from
the data's start (RK4 at h = 0.01 s), one element:
  vldm      the demo's network (16 x 16 tanh on der(speed) reading speed, residual) on the VLDM's
            extra-resistance data (as bench_step_cost.py). The core's gradient is not exact here
            (the sampled driver's held values and the state events, see neural/core_gradient.py):
            it is forced, to measure its cost and how far it is from the torch solver's gradient.
  dc_drive  8 x 8 tanh on der(speed) reading speed and current (gates, ANN gate 0.3) on the DC
            drive's windage data: the core's gradient is exact and training uses it.
Per case, best of --repeats, alternately: the floor (benchmarks/plain_fmu_loop.c, RK4 over the
same span), the loss forward and backward by the torch solver, and by the core (Trainer.batch_loss,
its sensor and residuals in torch either way), and the core's two C runs alone; per step and as
ratios to the floor. Then the gradients against each other (cosine, relative difference) and
against central differences of the loss on the three parameters of largest gradient.

    python benchmarks/bench_gradient_core.py [--span 20] [--repeats 3] [--case vldm --case dc_drive]
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from bench_core import build_floor, run_floor
from fmubuilder.build import example_fmu
from fmubuilder.data import read_sidecar
from fmubuilder.examples_zoo import cached_data, example_data_sets
from fmubuilder.fmi import Fmu, read_model_info
from fmubuilder.hybridize.evaluate import read_data
from fmubuilder.neural import NeuralFMU, TopologyConfig, core_gradient, train
from fmubuilder.neural.solve import simulate
from fmubuilder.neural.train import Trainer, TrainSettings

STEP = 0.01
CASES = {
    "vldm": ("extra_resistance", TopologyConfig(channels=["der(speed)"], inputs=["speed"], hidden=[16, 16],
                                                kind="residual")),
    "dc_drive": ("windage", TopologyConfig(channels=["der(speed)"], inputs=["speed", "current"], hidden=[8, 8],
                                           kind="gates")),
}


def trainer_for(case: str, span: float) -> Trainer:
    variant, config = CASES[case]
    sets = [s for s in example_data_sets(case) if s.variant.key == variant]
    paths, _ = cached_data(sets)
    train_csv = next(path for s, path in zip(sets, paths) if s.cycle.role == "train")
    fmu = example_fmu(case)
    whole = read_data(train_csv, read_model_info(fmu))
    stop = float(whole.time[np.searchsorted(whole.time, whole.start + span, side="right") - 1])
    data = whole.window(whole.start, stop)
    settings = TrainSettings(element_length=span, solver="rk4", step_size=STEP, optimizer="lbfgs", progress=False,
                             sensor_lag=data.sensor_lag)
    torch.manual_seed(0)
    model = NeuralFMU(fmu, TopologyConfig.from_dict(config.to_dict()), read_sidecar(train_csv)["start_values"])
    trainer = Trainer(model, data, settings, time.perf_counter())
    trainer.prepare()
    with torch.no_grad():      # away from the neutral start: every parameter has a gradient
        if config.kind == "gates":
            model.topology.gate_ann.fill_(0.3)
        for parameter in model.topology.ann.parameters():
            parameter.add_(0.05 * torch.randn_like(parameter))
    return trainer


def torch_solver(model, duration, step_size, *, starts, record, solver, inputs=None, keep_final_state=False):
    return simulate(model, duration, step_size, starts=starts, record=record, solver=solver, inputs=inputs,
                    keep_final_state=keep_final_state)


def forced_core(model, duration, step_size, *, starts, record, solver, inputs=None, keep_final_state=False):
    """The core's gradient whatever the model (strict=False: state resets let pass)."""
    return core_gradient.CoreElements(model, duration, step_size, starts, record, solver, inputs,
                                      strict=False).trajectory(keep_final_state)


def loss_with_gradient(trainer: Trainer, simulator) -> tuple[float, torch.Tensor, float]:
    """(loss, flat gradient, seconds) of one loss evaluation with `simulator` in the training."""
    model = trainer.model
    model.zero_grad()
    saved = train.simulate_for_loss
    train.simulate_for_loss = simulator
    try:
        started = time.perf_counter()
        loss = trainer.batch_loss(trainer.elements, carry=False)
        loss.backward()
        seconds = time.perf_counter() - started
    finally:
        train.simulate_for_loss = saved
    parameters = [p for p in model.topology.parameters() if p.requires_grad]
    flat = torch.cat([p.grad.flatten() if p.grad is not None else torch.zeros(p.numel(), dtype=p.dtype)
                      for p in parameters])
    return float(loss.detach()), flat, seconds


def core_runs(trainer: Trainer) -> tuple[float, float]:
    """Seconds of the core's forward run and of its run with sensitivities (one element)."""
    elements = core_gradient.CoreElements(trainer.model, trainer.element_duration, trainer.step,
                                          [e.start for e in trainer.elements], trainer.recorded,
                                          trainer.settings.solver, trainer.inputs, strict=False)
    started = time.perf_counter()
    elements._forward(False)
    forward = time.perf_counter() - started
    weights = np.ones((len(elements.tables[0]), len(trainer.recorded)))
    started = time.perf_counter()
    elements._run(0, weights)
    return forward, time.perf_counter() - started


def central_differences(trainer: Trainer, indices) -> list[float]:
    """d loss / d parameter by central differences of the torch solver's loss (no gradient)."""
    parameters = [p for p in trainer.model.topology.parameters() if p.requires_grad]
    where = [(p, i) for p in parameters for i in range(p.numel())]
    values = []
    for index in indices:
        parameter, i = where[index]
        base = float(parameter.data.view(-1)[i])
        delta = 1e-6 * max(1.0, abs(base))
        losses = []
        for value in (base + delta, base - delta):
            parameter.data.view(-1)[i] = value
            with torch.no_grad():
                losses.append(float(trainer.batch_loss(trainer.elements, carry=False)))
        parameter.data.view(-1)[i] = base
        values.append((losses[0] - losses[1]) / (2 * delta))
    return values


def run_case(case: str, span: float, repeats: int, program: Path) -> None:
    trainer = trainer_for(case, span)
    model = trainer.model
    steps = round(trainer.element_duration / STEP) * len(trainer.elements)
    exact = core_gradient.exact_in_core(model)
    core = (core_gradient.simulate_for_loss if exact else forced_core)
    times = {"floor": [], "torch": [], "core": [], "forward": [], "sensitivities": []}
    with Fmu(model.fmu_path) as fmu:
        names = [v.name for v in fmu.info.states]
        for _ in range(repeats):
            times["floor"].append(run_floor(program, fmu, names, span, STEP)[0] * steps / round(span / STEP))
            loss_torch, grad_torch, seconds = loss_with_gradient(trainer, torch_solver)
            times["torch"].append(seconds)
            loss_core, grad_core, seconds = loss_with_gradient(trainer, core)
            times["core"].append(seconds)
            forward, sensitivities = core_runs(trainer)
            times["forward"].append(forward)
            times["sensitivities"].append(sensitivities)
    best = {key: min(values) for key, values in times.items()}
    per_step = {key: value * 1e6 / steps for key, value in best.items()}
    print(f"\n{case}: {trainer.element_duration:g} s of training data, {steps} RK4 steps of {STEP} s, "
          f"{sum(p.numel() for p in model.topology.parameters() if p.requires_grad)} trained parameters, "
          f"core gradient {'exact, used by training' if exact else 'NOT exact (forced here)'}; best of {repeats}")
    print("| what | us per step | ratio to the floor |\n|---|---|---|")
    rows = (("floor: plain C loop, RK4", "floor"), ("loss + gradient, torch batch solver", "torch"),
            ("loss + gradient, core (forward sensitivities)", "core"), ("  core: the forward run", "forward"),
            ("  core: the run with sensitivities", "sensitivities"))
    for label, key in rows:
        print(f"| {label} | {per_step[key]:.1f} | {best[key] / best['floor']:.0f} |")
    print(f"torch / core: {best['torch'] / best['core']:.0f} times")
    cosine = float(grad_core @ grad_torch / (grad_core.norm() * grad_torch.norm()))
    relative = float((grad_core - grad_torch).norm() / grad_torch.norm())
    print(f"loss: core {loss_core:.9g}, torch {loss_torch:.9g}; gradient core vs torch: cosine {cosine:.6f}, "
          f"|difference| / |torch| {relative:.2e}")
    largest = np.argsort(-np.abs(grad_torch.numpy()))[:3].tolist()
    for index, fd in zip(largest, central_differences(trainer, largest)):
        print(f"  parameter {index}: central differences {fd:.6g}, torch {float(grad_torch[index]):.6g}, "
              f"core {float(grad_core[index]):.6g}")
    model.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--span", type=float, default=20.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--case", action="append", choices=sorted(CASES))
    args = parser.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as folder:
        program = build_floor(Path(folder))
        for case in args.case or ["vldm", "dc_drive"]:
            run_case(case, args.span, args.repeats, program)


if __name__ == "__main__":
    main()
