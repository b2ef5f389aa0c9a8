"""What the data and an ANN's inputs allow on the VLDM's extra loss, without any training through the solver.

The truth (examples/vldm/model.c, VLDM_TRUTH_EXTRA_LOSS) adds EXTRA_LOSS_FRACTION * |motor_torque *
motor_speed| to the power the battery delivers, on der(energy). For each set of ANN inputs, the
16x16 tanh ANN of `hybridize` on der(energy) is fitted without the solver to that loss at the
truth's own values of the inputs along the training part (the first 80 % of the CADC run), then
the declared FMU with that ANN is simulated (RK4, h = 0.01 s, through the sensor lag) over the
whole CADC run and the WLTC class 2 test run: MSE / noise variance per signal. The truth FMU and
the plain FMU are scored the same way. Inputs that hold the loss as a function reach the floor
here; inputs that do not, stay above it whatever the training does.

With --leaf-fit, what the data themselves allow a free function of each input set, without the
solver: der(energy) is a leaf of this model (nothing depends on the energy) and the loss changes
nothing upstream, so the hybrid's power and energy are the plain run's plus the ANN's value and
its integral along the plain run, both linear in the ANN's last layer. The hidden layers are the
warm start's fit to the plain run's estimate of the missing term (weight decay
warm_start.WEIGHT_DECAY), then the last layer and the energy's start are the exact least squares
of the training part's measured power and energy (each over its noise variance) through the
sensor lag: the best that layer can do on those data. MSE / noise variance of power and energy
on the training part, the validation tail and the test run.

Then the warm start's target, the collocation estimate of the missing term (neural/collocation.py:
the measured power, equal to der(energy) in this model, minus the model's der(energy) in the run
with the measured states forced), against the truth's loss at the same times; and the same
difference taken from the plain model's own run, no state forced. Also how far the forced run's
speed and der(speed) lie from the truth's.

    python benchmarks/bench_loss_floor.py [--inputs "speed,der(speed)" --inputs "motor_torque,motor_speed"]
        [--estimates-only] [--leaf-fit]
"""
from __future__ import annotations

import argparse

import numpy as np
import torch

from fmubuilder.build import example_fmu
from fmubuilder.data import load_data, read_sidecar, sensor_reading
from fmubuilder.examples_zoo import cached_data, vldm_data_sets
from fmubuilder.fmi import read_model_info
from fmubuilder.hybridize import recipe, workflow
from fmubuilder.neural import NeuralFMU, TopologyConfig
from fmubuilder.neural.collocation import forced_channel_run, samples_along
from fmubuilder.neural.train import data_errors, simulate_over
from fmubuilder.neural.warm_start import WEIGHT_DECAY, fit_full_batch, scale_output_to_effect
from fmubuilder.simulation import simulate

STEP = 0.01
EXTRA_LOSS_FRACTION = 0.10      # examples/vldm/model.c
CHANNEL = "der(energy)"
DEFAULT_INPUTS = ["speed,der(speed)", "motor_torque,motor_speed", "motor_power"]
LEAF_FIT_INPUTS = ["speed,der(speed)", "driver.throttle,speed", "motor_torque,motor_speed", "motor_power,speed"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--inputs", action="append", help="comma-separated ANN inputs (repeatable)")
    parser.add_argument("--estimates-only", action="store_true", help="only the estimates of the missing term")
    parser.add_argument("--leaf-fit", action="store_true",
                        help="the ANN's last layer fitted exactly to the measured power and energy, per input set")
    args = parser.parse_args()
    torch.set_num_threads(1)
    sets = [d for d in vldm_data_sets() if d.variant.key == "extra_loss"]
    paths, _ = cached_data(sets)
    train_csv = next(p for p in paths if "_train_" in p.name)
    test_csv = next(p for p in paths if "_test_" in p.name)
    declared, truth = example_fmu("vldm"), example_fmu(sets[0].variant.fmu)
    info = read_model_info(declared)
    whole, test = load_data(train_csv, info), load_data(test_csv, info)
    split = whole.start + (1.0 - workflow.VALIDATION_SHARE) * (whole.stop - whole.start)
    starts = read_sidecar(train_csv)["start_values"], read_sidecar(test_csv)["start_values"]
    lag = read_sidecar(train_csv)["bench"]["lag"]
    runs = {"whole CADC": (whole, starts[0]), "test WLTC2": (test, starts[1])}
    names = list(whole.signals)
    # a measured output equal to der(energy) (the power) is read from the hybrid's derivative, as hybridize reads it
    aliases = workflow.channel_aliases(declared, info, CHANNEL, starts[0], whole.time, whole.start,
                                       whole.start + workflow.ALIAS_SPAN)
    if args.estimates_only:
        _estimates(declared, truth, info, _training_part(whole, split), starts[0])
        return
    if args.leaf_fit:
        input_sets = [s.split(",") for s in (args.inputs or LEAF_FIT_INPUTS)]
        _leaf_fits(declared, info, {"CADC": (whole, starts[0]), "WLTC2": (test, starts[1])}, split, lag, input_sets)
        return
    print(f"(MSE / noise variance per signal: {', '.join(names)}; RK4, h = {STEP} s)")
    print("| model | whole CADC | test WLTC2 | fit: relative error |\n|---|---|---|---|")
    plain = NeuralFMU(declared, TopologyConfig(), start_values=starts[0])
    print(f"| plain FMU | {' | '.join(_scores(plain, runs, lag, names, aliases, plain=True))} | - |", flush=True)
    plain.close()
    for inputs in [s.split(",") for s in (args.inputs or DEFAULT_INPUTS)]:
        torch.manual_seed(0)
        model = NeuralFMU(declared, TopologyConfig(channels=[CHANNEL], inputs=inputs, kind="residual", hidden=[16, 16]),
                          start_values=starts[0])
        x, target = _truth_along(truth, inputs, whole.start, split, starts[0])
        model.topology.initialise_scaling(x.numpy(), target.numpy())
        scale_output_to_effect(model.topology, target)
        fit_full_batch(model.topology, x, target, iterations=1000, bounded=False, weight_decay=0.0)
        with torch.no_grad():
            error = float(((model.topology.correction(x) - target) ** 2).mean() / (target ** 2).mean())
        print(f"| ANN reading {', '.join(inputs)}, fitted to the truth's loss | "
              f"{' | '.join(_scores(model, runs, lag, names, aliases))} | {error:.2g} |", flush=True)
        model.close()
    truth_model = NeuralFMU(truth, TopologyConfig(), start_values=starts[0])
    print(f"| truth FMU | {' | '.join(_scores(truth_model, runs, lag, names, aliases, plain=True))} | - |")
    truth_model.close()
    _estimates(declared, truth, info, _training_part(whole, split), starts[0])


def _training_part(whole, split: float):
    return whole.window(whole.start, float(whole.time[np.searchsorted(whole.time, split, side="right") - 1]))


def _estimates(declared, truth, info, train, start_values: dict) -> None:
    """The missing term of der(energy) estimated along the measured run, against the truth's loss."""
    seen = ["speed", "der(speed)"]      # what the forced run makes of them
    model = NeuralFMU(declared, TopologyConfig(channels=[CHANNEL], inputs=seen, kind="residual"),
                      start_values=start_values)
    lag = train.sensor_lag
    signals = train.input_signals(info)
    estimates = {}      # the warm start's two: along the forced run and along the plain run
    for force in (True, False):
        run = forced_channel_run(model, train, STEP, "rk4", recipe.COLLOCATION_WINDOW, signals, lag, force)
        times, values, fmu, measured, mask = samples_along(run, model, train, recipe.COLLOCATION_WINDOW, lag)
        estimates[force] = (times, values, (measured - fmu)[:, 0], mask[:, 0])
    model.close()
    times, forced_values, forced, keep = estimates[True]
    plain_times, _, unforced, valid = estimates[False]
    assert np.array_equal(times, plain_times), "both runs are sampled on the data's grid"
    truth_values, true = _truth_along(truth, seen, train.start, train.stop, start_values, times)
    true = true.numpy()[:, 0]
    for j, name in enumerate(seen):
        off = forced_values[keep, j] - truth_values.numpy()[keep, j]
        print(f"{name} in the forced run: {np.sqrt(np.mean(off ** 2)):.3g} rms off the truth's "
              f"(whose rms is {np.sqrt(np.mean(truth_values.numpy()[keep, j] ** 2)):.3g})")
    print(f"\nthe missing term of {CHANNEL} estimated along the training part ({int(keep.sum())} points; the truth's "
          f"loss: mean {true[keep].mean():.0f} W, rms {np.sqrt(np.mean(true[keep] ** 2)):.0f} W)")
    print("| estimate | minus the truth's loss: mean [W] | rms [W] | correlation with it |\n|---|---|---|---|")
    for label, estimate, where in (("along the run with the measured states forced", forced, keep),
                                   ("along the plain model's own run, nothing forced", unforced, valid)):
        error = estimate[where] - true[where]
        print(f"| {label} | {error.mean():.3g} | {np.sqrt(np.mean(error ** 2)):.3g} | "
              f"{np.corrcoef(estimate[where], true[where])[0, 1]:.2f} |")


def _leaf_fits(declared, info, runs: dict, split: float, lag: float, input_sets: list[list[str]]) -> None:
    """The last layer's exact least-squares fit per input set (see the module docstring)."""
    whole, start_values = runs["CADC"]
    train = _training_part(whole, split)
    recorded = sorted({name for inputs in input_sets for name in inputs} | {"energy", CHANNEL})
    model = NeuralFMU(declared, TopologyConfig(), start_values=start_values)
    try:
        plain = {label: simulate_over(model, data, STEP, "rk4", values, plain=True, record=recorded)
                 for label, (data, values) in runs.items()}
    finally:
        model.close()
    print("(MSE / noise variance of power and energy; the hidden layers fitted to the plain run's estimate)")
    print("| ANN inputs | last layer | training part | validation tail | test WLTC2 |\n|---|---|---|---|---|")
    for inputs in input_sets:
        torch.manual_seed(0)
        model = NeuralFMU(declared, TopologyConfig(channels=[CHANNEL], inputs=inputs, kind="residual", hidden=[16, 16]),
                          start_values=start_values)
        run = forced_channel_run(model, train, STEP, "rk4", recipe.COLLOCATION_WINDOW, train.input_signals(info),
                                 lag, force=False)
        _, values, fmu, measured, mask = samples_along(run, model, train, recipe.COLLOCATION_WINDOW, lag)
        keep = mask[:, 0]
        x, target = torch.from_numpy(values[keep]), torch.from_numpy((measured - fmu)[keep][:, :1])
        model.topology.initialise_scaling(x.numpy(), target.numpy())
        scale_output_to_effect(model.topology, target)
        fit_full_batch(model.topology, x, target, iterations=500, weight_decay=WEIGHT_DECAY)
        shown = {label: _shown_per_weight(model.topology, plain[label], runs[label][0], inputs, lag) for label in runs}
        fitted = model.topology.ann[-1]
        start = np.concatenate([fitted.weight.detach().numpy()[0], fitted.bias.detach().numpy()])
        training = whole.time <= split
        least_squares, offset = _last_layer_least_squares(whole, shown["CADC"], training)
        for label, theta, shift in (("the estimate's fit", start, 0.0), ("least squares", least_squares, offset)):
            cells = [_leaf_scores(whole, shown["CADC"], theta, training, shift), _leaf_scores(whole, shown["CADC"], theta, ~training),
                     _leaf_scores(runs["WLTC2"][0], shown["WLTC2"], theta)]
            print(f"| {', '.join(inputs)} | {label} | {' | '.join(cells)} |", flush=True)
        model.close()


def _shown_per_weight(topology, run, data, inputs: list[str], lag: float) -> dict:
    """{signal: (what its sensor shows with the last layer at zero, what each of the layer's entries
    adds per unit)} for power (the hybrid's der(energy)) and energy (its integral)."""
    time = np.asarray(run.time, dtype=float)
    x = torch.from_numpy(np.stack([np.asarray(run[name], dtype=float) for name in inputs], axis=1))
    layer = topology.ann[-1]
    kept = layer.weight.detach().clone(), layer.bias.detach().clone()
    with torch.no_grad():
        layer.weight.zero_()
        layer.bias.zero_()
        zero = topology.correction(x)[:, 0].numpy()
        columns = []
        for k in range(layer.weight.shape[1] + 1):
            (layer.weight[0, k] if k < layer.weight.shape[1] else layer.bias[0]).fill_(1.0)
            columns.append(topology.correction(x)[:, 0].numpy() - zero)
            layer.weight.zero_()
            layer.bias.zero_()
        layer.weight.copy_(kept[0])
        layer.bias.copy_(kept[1])
    per_weight = np.stack(columns, axis=1)

    def shown(values):
        return sensor_reading(time, values, data.time, lag)

    power = np.asarray(run[CHANNEL], dtype=float) + zero
    energy = np.asarray(run["energy"], dtype=float) + _integral(time, zero)
    integrals = _integral(time, per_weight)
    return {"power": (shown(power), np.stack([shown(c) for c in per_weight.T], axis=1)),
            "energy": (shown(energy), np.stack([shown(c) for c in integrals.T], axis=1))}


def _integral(time: np.ndarray, values: np.ndarray) -> np.ndarray:
    """The trapezoidal integral from the first record (an event's two records add nothing)."""
    steps = np.diff(time).reshape(-1, *([1] * (values.ndim - 1)))
    return np.concatenate([np.zeros_like(values[:1]), np.cumsum(0.5 * (values[1:] + values[:-1]) * steps, axis=0)])


def _last_layer_least_squares(data, shown: dict, rows: np.ndarray) -> tuple[np.ndarray, float]:
    """The last layer's entries and the energy's start offset minimising the training part's MSE of
    power and energy, each over its noise variance."""
    blocks, targets = [], []
    for name in ("power", "energy"):
        base, per_weight = shown[name]
        weight = 1.0 / np.sqrt(data.noise_variance(name) * rows.sum())
        offset = np.full((rows.sum(), 1), weight if name == "energy" else 0.0)
        blocks.append(np.hstack([per_weight[rows] * weight, offset]))
        targets.append((data.signals[name][rows] - base[rows]) * weight)
    solution = np.linalg.lstsq(np.vstack(blocks), np.concatenate(targets), rcond=None)[0]
    return solution[:-1], float(solution[-1])


def _leaf_scores(data, shown: dict, theta: np.ndarray, rows=None, energy_offset: float = 0.0) -> str:
    rows = np.ones(data.time.size, dtype=bool) if rows is None else rows
    cells = []
    for name in ("power", "energy"):
        base, per_weight = shown[name]
        error = base + per_weight @ theta + (energy_offset if name == "energy" else 0.0) - data.signals[name]
        cells.append(f"{np.mean(error[rows] ** 2) / data.noise_variance(name):.3g}")
    return ", ".join(cells)


def _truth_along(truth, inputs: list[str], start: float, stop: float, start_values: dict, times=None):
    """The inputs' values and the truth's extra loss along the truth's run over [start, stop]: every
    0.1 s, or at `times`."""
    recorded = list(dict.fromkeys([*inputs, "motor_torque", "motor_speed"]))
    run = simulate(truth, start_time=start, stop_time=stop, start_values=start_values, variables=recorded,
                   solver="rk4", step_size=STEP, output_interval=0.1 if times is None else STEP)
    at = run.time if times is None else times
    values = {name: np.interp(at, run.time, np.asarray(run[name], dtype=float)) for name in recorded}
    x = np.stack([values[name] for name in inputs], axis=1) if inputs else np.zeros((len(at), 0))
    loss = EXTRA_LOSS_FRACTION * np.abs(values["motor_torque"] * values["motor_speed"])
    return torch.from_numpy(x), torch.from_numpy(loss[:, None])


def _scores(model, runs, lag, names, aliases: dict, plain: bool = False) -> list[str]:
    cells = []
    for data, start_values in runs.values():
        run = simulate_over(model, data, STEP, "rk4", start_values, plain=plain, aliases=aliases)
        errors = data_errors(data, run, lag, aliases)
        cells.append(", ".join(f"{errors[n]['mse'] / data.noise_variance(n):.3g}" for n in names))
    return cells


if __name__ == "__main__":
    main()
