"""How close the NeuralFMU's ANN can get when it is given the true effect: its representation's ceiling.

For each DC drive truth (examples/dc_drive/model.c holds the effects' formulas) the truth FMU is
simulated over the training part of the training run (its first 80 %, as `hybridize` trains), the
true missing term is computed from the truth's states along it, and the ANN (the topology
`hybridize` builds: residual, on the channels and inputs the workflow chooses) is fitted to it
directly, supervised, with the warm start's full-batch fit (neural/warm_start.fit_full_batch); no
solver in the loop. The hybrid is then simulated over the training part and the test run (the
engine's RK4 at 0.01 s, the sensors' lag applied) and scored as MSE / noise variance per signal
(1 = the noise floor). With --collocation the same ANN is fitted instead to the collocation
estimate of the effect from the measured data (what the workflow's warm start does). With two
derivatives each reads its own inputs, as the workflow wires them; --shared-inputs (or --inputs)
gives every derivative all the inputs in one network.

Printed per variant: the fit's relative error on the true effect (MSE / the effect's mean square;
all samples and those within NEAR_ZERO rad/s of speed 0; per derivative when there are two), and the
train / test MSE over the noise floor per signal.

    python benchmarks/bench_representation.py [--cases stribeck,coulomb,speed_current_loss]
        [--hidden 16,16] [--activation tanh] [--iterations N] [--weight-decay D] [--input-scale std|maxabs|F]
        [--inputs speed,current | --shared-inputs] [--collocation [--target pointwise|integral]
        [--integral-window S]] [--unbounded]
"""
from __future__ import annotations

import argparse
import math

import numpy as np
import torch

from fmubuilder.build import example_fmu
from fmubuilder.data import first_order_lag, read_sidecar
from fmubuilder.examples_zoo import cached_data, example_data_sets
from fmubuilder.fmi import read_model_info
from fmubuilder.hybridize.evaluate import read_data
from fmubuilder.simulation.results import sample_settled
from fmubuilder.hybridize.workflow import VALIDATION_SHARE
from fmubuilder.neural.model import NeuralFMU
from fmubuilder.neural.system import simulate_hybrid
from fmubuilder.neural.topology import TopologyConfig
from fmubuilder.neural.train import TrainSettings, measured_initial_states
from fmubuilder.neural.warm_start import WEIGHT_DECAY, fit_full_batch, scale_output_to_effect
from fmubuilder.simulation import simulate

STEP = 0.01
NEAR_ZERO = 5.0     # rad/s: the band around speed 0 where the sign-type frictions change
# The channels and inputs `hybridize` chooses per truth (benchmarks/bench_inputs.py), and per
# channel the inputs its correction reads.
WORKFLOW_CHOICE = {
    "stribeck": (["der(speed)"], ["speed"], [["speed"]]),
    "coulomb": (["der(speed)"], ["speed"], [["speed"]]),
    "speed_current_loss": (["der(energy)"], ["current", "speed"], [["current", "speed"]]),
    "two_effects": (["der(energy)", "der(speed)"], ["current", "speed"], [["current", "speed"], ["speed"]]),
}
INERTIA, SMOOTHING = 0.01, 1.0     # examples/dc_drive/model.c


def true_effect(variant: str, channel: str, states: dict) -> np.ndarray:
    """The truth's term missing from the declared model's `channel` derivative (model.c)."""
    w, i = states["speed"], states["current"]
    stribeck = 0.08 * np.tanh(w / SMOOTHING) * np.exp(-(w / 40.0) ** 2)
    loss = 0.01 * np.abs(w * i)
    effects = {
        ("stribeck", "der(speed)"): -stribeck / INERTIA,
        ("coulomb", "der(speed)"): -0.05 * np.tanh(w / SMOOTHING) / INERTIA,
        ("speed_current_loss", "der(energy)"): loss,
        ("two_effects", "der(speed)"): -stribeck / INERTIA,
        ("two_effects", "der(energy)"): loss,
    }
    return effects[(variant, channel)]


def case_data(variant: str):
    sets = [s for s in example_data_sets("dc_drive") if s.variant.key == variant]
    paths, _ = cached_data(sets)
    by_role = {s.cycle.role: (p, s) for s, p in zip(sets, paths)}
    return by_role["train"], by_role["test"]


def run_case(variant: str, args) -> list[list[str]]:
    (train_path, data_set), (test_path, _) = case_data(variant)
    declared = example_fmu("dc_drive")
    info = read_model_info(declared)
    run = read_data(train_path, info)
    split = run.start + (1.0 - VALIDATION_SHARE) * (run.stop - run.start)
    train = run.window(run.start, float(run.time[np.searchsorted(run.time, split, side="right") - 1]))
    test = read_data(test_path, info)
    channels, inputs, channel_inputs = WORKFLOW_CHOICE[variant]
    inputs = args.inputs.split(",") if args.inputs else inputs
    if args.inputs or args.shared_inputs:
        channel_inputs = []        # every channel reads every input (before per-channel inputs)
    config = TopologyConfig(channels=channels, inputs=inputs, hidden=[int(h) for h in args.hidden.split(",")],
                            activation=args.activation, kind="residual", channel_inputs=channel_inputs)
    torch.manual_seed(0)
    model = NeuralFMU(declared, config, start_values=train.start_values)
    try:
        x, target, speed, average = samples(model, variant, data_set, train, args.collocation, args)
        initialise(model, train, args.input_scale, x)
        scale_output_to_effect(model.topology, target)
        fit_full_batch(model.topology, x, target, args.iterations, weight_decay=args.weight_decay,
                       bounded=not args.unbounded, average=average)
        with torch.no_grad():
            fitted = model.topology.correction(x)
        truth_x, truth_target, truth_speed, _ = samples(model, variant, data_set, train, False, args)
        with torch.no_grad():
            on_truth = model.topology.correction(truth_x)
        fit = "; ".join((f"{c}: " if len(channels) > 1 else "")
                        + relative_errors(on_truth[:, [j]], truth_target[:, [j]], truth_speed)
                        for j, c in enumerate(channels))
        errors = {"train": scored(model, train), "test": scored(model, test)}
    finally:
        model.close()
    bench = read_sidecar(test_path)["bench"]
    rows = []
    for signal in train.names:
        floor = bench["noise_std"][signal] ** 2 / bench["runs"]
        wiring = "; ".join(f"{c} <- {', '.join(names)}" for c, names in zip(channels, channel_inputs)) \
            if channel_inputs else f"{', '.join(channels)} <- {', '.join(inputs)}"
        rows.append([variant, wiring, signal, fit,
                     f"{errors['train'][signal]['mse'] / floor:.3g}", f"{errors['test'][signal]['mse'] / floor:.3g}"])
    del fitted
    return rows


def scored(model, data) -> dict:
    """{signal: {"mse", ...}} of the hybrid over the data, the engine's RK4, through the sensors'
    lag. An output equal to a corrected derivative (the DC drive's power is der(energy)) reads the
    hybrid's derivative, as the exported hybrid FMU does (hybridize's output aliases)."""
    aliases = {"power": "der(energy)"} if "der(energy)" in model.config.channels else {}
    original = dict(model.start_values)
    model.start_values.update(measured_initial_states(model, data))
    model.start_values.update(data.start_values)
    try:
        names = list(dict.fromkeys([aliases.get(n, n) for n in data.signals]))
        result = simulate_hybrid(model, start_time=data.start, stop_time=data.stop, variables=names, solver="rk4",
                                 step_size=STEP, output_interval=STEP, inputs=data.input_signals(model.info))
    finally:
        model.start_values = original
    errors = {}
    for name in data.signals:
        seen = first_order_lag(result.time, np.asarray(result[aliases.get(name, name)], dtype=float), data.sensor_lag)
        diff = sample_settled(result.time, seen, data.time) - data.signals[name]
        errors[name] = {"mse": float(np.mean(diff ** 2))}
    return errors


def samples(model, variant: str, data_set, train, collocation: bool, args):
    """(raw ANN inputs, target, speed, window means or None) along the training part: the true
    effect on the truth's trajectory, or the collocation estimate from the measured data (its
    pointwise or its integral form)."""
    if collocation:
        from fmubuilder.neural.train import Trainer
        from fmubuilder.neural.warm_start import collocation_targets, integral_targets
        settings = TrainSettings(solver="rk4", step_size=STEP, ccpt_window=0.5, progress=False,
                                 sensor_lag=train.sensor_lag, warm_start_target=args.target,
                                 integral_window=args.integral_window)
        trainer = Trainer(model, train, settings, 0.0)
        trainer.inputs = train.input_signals(model.info)
        if args.target == "integral":
            x, target, average = integral_targets(trainer)
        else:
            (x, target), average = collocation_targets(trainer), None
        speed_column = model.config.inputs.index("speed") if "speed" in model.config.inputs else None
        speed = x[:, speed_column].numpy() if speed_column is not None else np.full(len(x), np.inf)
        return x, target, speed, average
    states = [v.name for v in model.info.states]
    starts = {**train.start_values, **data_set.variant.truth_parameters}
    result = simulate(example_fmu(data_set.variant.fmu), start_time=train.start, stop_time=train.stop,
                      start_values=starts, variables=list(dict.fromkeys(states + model.config.inputs)),
                      solver="rk4", step_size=STEP, output_interval=STEP)
    values = {name: np.asarray(result[name], dtype=float) for name in dict.fromkeys(states + model.config.inputs)}
    x = torch.from_numpy(np.stack([values[name] for name in model.config.inputs], axis=1))
    target = torch.from_numpy(np.stack([true_effect(variant, c, values) for c in model.config.channels], axis=1))
    return x, target, values["speed"], None


def initialise(model, train, input_scale: str, x: torch.Tensor) -> None:
    """Pre-/post-processing from the plain FMU's run over the training part (as the trainer sets
    them), then the input scale replaced if asked."""
    names = model.config.inputs + model.config.channels
    with torch.no_grad(), model.topology.ann_off():
        result = simulate_hybrid(model, start_time=train.start, stop_time=train.stop, variables=names,
                                 solver="rk4", step_size=STEP, output_interval=STEP)
    inputs = np.stack([np.asarray(result[n], dtype=float) for n in model.config.inputs], axis=1)
    channels = np.stack([np.asarray(result[n], dtype=float) for n in model.config.channels], axis=1)
    model.topology.initialise_scaling(inputs, channels)
    if input_scale == "std":
        return
    with torch.no_grad():
        if input_scale == "maxabs":
            model.topology.pre_scale.copy_(1.0 / (x - model.topology.pre_shift).abs().max(dim=0).values)
        else:
            model.topology.pre_scale.mul_(float(input_scale))


def relative_errors(fitted: torch.Tensor, target: torch.Tensor, speed: np.ndarray) -> str:
    squared = ((fitted - target) ** 2).numpy()
    size = float((target ** 2).mean())
    near = np.abs(speed) < NEAR_ZERO
    share = squared[near].sum() / max(squared.sum(), 1e-300)
    return (f"{squared.mean() / size:.3g} (near 0: {squared[near].mean() / size if near.any() else math.nan:.3g}, "
            f"{share:.0%} of it)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default="stribeck,coulomb,speed_current_loss")
    parser.add_argument("--hidden", default=",".join(str(h) for h in TopologyConfig().hidden))
    parser.add_argument("--activation", default=TopologyConfig().activation)
    parser.add_argument("--iterations", type=int, default=TrainSettings().warm_start_iterations)
    parser.add_argument("--weight-decay", type=float, default=WEIGHT_DECAY,
                        help="the fit's L2 penalty on the ANN's weights (warm_start.WEIGHT_DECAY; 0: none)")
    parser.add_argument("--input-scale", default="std", help="std (default), maxabs or a factor on the std's")
    parser.add_argument("--inputs", default="", help="override the workflow's inputs, comma-separated")
    parser.add_argument("--shared-inputs", action="store_true",
                        help="every channel reads all inputs (one network), not its own inputs")
    parser.add_argument("--collocation", action="store_true",
                        help="fit to the collocation estimate from the data instead of the true effect")
    parser.add_argument("--target", default="pointwise", choices=["pointwise", "integral"],
                        help="with --collocation: local slopes (pointwise) or window increments (integral)")
    parser.add_argument("--integral-window", type=float, default=TrainSettings().integral_window,
                        help="seconds per window of the integral target")
    parser.add_argument("--unbounded", action="store_true", help="without the fit's range bound")
    args = parser.parse_args()
    rows = []
    for variant in args.cases.split(","):
        rows += run_case(variant.strip(), args)
    source = "true effect"
    if args.collocation:
        source = "collocation estimate" if args.target == "pointwise" else \
            f"integral collocation target ({args.integral_window:g} s windows)"
    source += ", unbounded" if args.unbounded else ""
    print(f"\nANN {args.hidden} {args.activation}, input scale {args.input_scale}, {args.iterations} L-BFGS "
          f"iterations, weight decay {args.weight_decay:g}, fitted to the {source}; MSE / noise variance (1 = floor):\n")
    print("| case | channels <- inputs | signal | fit error on the true effect (rel. MSE) | train | test |")
    print("|---|---|---|---|---|---|")
    for row in rows:
        print("| " + " | ".join(row) + " |")


if __name__ == "__main__":
    main()
