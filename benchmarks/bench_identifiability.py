"""What the training and validation data determine on the test run: how far a change of the missing
effect that they cannot see moves the test signals.

For each case (an example's truth variant) the missing effect is given a family of shapes, as a
correction of the declared model at the truth's derivatives, reading the truth's own variables:

- the ANN's last layer: the hybrid's 16x16 tanh ANN (`hybridize`'s, seeded) with its pre- and
  post-processing set from the plain run, its last layer moved along the directions its hidden units
  span over the training run (those `neural/last_layer.py` searches along; the strongest first);
- the truth's form, where the term library holds it (a power law of one variable): its terms, one
  coefficient each.

Each shape's effect on every measured signal, at the samples of the training run (the fit part and
the validation tail) and of the test run, is the central difference of two engine simulations (RK4,
h = 0.01 s, through the sensor lag, as every model is scored) around the truth FMU (the model that
made the data, which errs only by their noise), at a small amplitude: the signals' linear response.
A change of the effect is *hidden* when it raises no signal's MSE / noise variance on the fit part
or on the validation tail by more than one standard deviation of what the noise alone does to that
ratio there (choice.score_spread: sqrt(2 / n) with n blocks of 1.2 s; every part simulated from the
run's start, as the candidates are scored). Printed per test signal: the largest rise of its MSE /
noise variance that a hidden change can cause, for the k strongest shapes of each family,
bracketed: reached by a hidden change - a bound no hidden change exceeds (_largest_rises).

The check, without the linear model: the truth FMU with the change of the ANN's last layer (all its
shapes) that moves the test signal of the largest rise most, shrunk until the simulation itself
finds it hidden on the fit part and the validation tail, is scored against the data on every role,
beside the truth FMU alone (MSE / noise variance per signal). Where it disagrees with the linear
responses (a closed loop whose relays and limits answer changes of that size otherwise), the
bracket does not hold for that case.

A large number says that the data leave the test signal open: models that the training and
validation data cannot tell apart differ there by that much, whatever the training does, and only a
family that holds the effect with fewer shapes (the term library's forms) can be pinned. A bound
below 1 says that every model of that family the data accept predicts the test signal to within
its noise.

    python benchmarks/bench_identifiability.py [--cases dc_drive,vldm | vldm:extra_loss,...] [--amplitude A]
"""
from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np
import torch
from scipy.linalg import eigh
from scipy.optimize import minimize

from fmubuilder.build import example_fmu
from fmubuilder.examples_zoo import cached_data, example_data_sets
from fmubuilder.fmi import read_model_info
from fmubuilder.hybridize import workflow
from fmubuilder.hybridize.choice import score_spread
from fmubuilder.hybridize.evaluate import read_data
from fmubuilder.neural import NeuralFMU, TopologyConfig
from fmubuilder.neural.last_layer import _directions
from fmubuilder.neural.train import predicted_at_samples, simulate_over

STEP = 0.01
# The truths' effects (examples/*/model.c): derivative -> the variables it reads, and the truth's form
# where the term library holds it.
CASES = {
    ("dc_drive", "windage"): ({"der(speed)": ["speed"]}, [("speed", "w*|w|")]),
    ("dc_drive", "extra_heating"): ({"der(temperature)": ["current"]}, [("current", "w^2")]),
    ("dc_drive", "stribeck"): ({"der(speed)": ["speed"]}, None),
    ("dc_drive", "coulomb"): ({"der(speed)": ["speed"]}, None),
    ("dc_drive", "speed_current_loss"): ({"der(energy)": ["speed", "current"]}, None),
    ("dc_drive", "two_effects"): ({"der(energy)": ["speed", "current"], "der(speed)": ["speed"]}, None),
    ("vldm", "extra_resistance"): ({"der(speed)": ["speed"]}, [("speed", "w"), ("speed", "w*|w|")]),
    ("vldm", "extra_loss"): ({"der(energy)": ["motor_torque", "speed"]}, None),
}
# Numbers of the strongest shapes reported (each channel's, with two corrected derivatives).
SHAPES = (1, 2, 3, 4, 6, 8)
# The check's change shrunk by 0.7 at most this many times until the simulation finds it hidden.
CHECK_SHRINKS = 12


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default="dc_drive,vldm", help="examples, or example:variant, comma-separated")
    parser.add_argument("--amplitude", type=float, default=1e-2,
                        help="each shape's size in the simulations, per unit of the derivative's spread (default 1e-2)")
    args = parser.parse_args()
    try:
        cases = _cases(args.cases)
        if not args.amplitude > 0:
            raise ValueError(f"--amplitude: give a positive number, got {args.amplitude}")
    except ValueError as exc:
        sys.exit(f"error: {exc}")
    torch.set_num_threads(1)
    rows = []
    for case in cases:
        started = time.perf_counter()
        rows += _case_rows(case, args.amplitude)
        print(f"done: {' '.join(case)} ({time.perf_counter() - started:.0f} s)", flush=True)
    print("\nLargest rise of the test run's MSE / noise variance, per signal, under a change of the effect that "
          "raises no signal's MSE / noise variance on the fit part or the validation tail by more than the noise's "
          "spread (the k strongest shapes of each family; reached - at most):\n")
    print("| case | family | shapes | rise per test signal |\n|---|---|---|---|")
    for row in rows:
        print("| " + " | ".join(row) + " |")


def _cases(spec: str) -> list[tuple[str, str]]:
    chosen = []
    for item in spec.split(","):
        example, _, variant = item.strip().partition(":")
        matching = [case for case in CASES if case[0] == example and variant in ("", case[1])]
        if not matching:
            known = ", ".join(f"{e}:{v}" for e, v in CASES)
            raise ValueError(f"--cases: no case '{item.strip()}'; choose among {known}")
        chosen += [case for case in matching if case not in chosen]
    return chosen


class _Run:
    """One data set, its start values and the outputs read from corrected derivatives."""

    def __init__(self, path, info, start_values: dict, aliases: dict):
        self.data = read_data(path, info)
        self.start_values = {**self.data.start_values, **start_values}
        self.aliases = aliases

    def signals(self, model: NeuralFMU) -> dict:
        run = simulate_over(model, self.data, STEP, "rk4", self.start_values, aliases=self.aliases)
        if run.terminated_early:
            raise RuntimeError(f"the hybrid stopped at t = {run.stop_time:g} s")
        return {n: predicted_at_samples(self.data, run, n, self.data.sensor_lag, self.aliases) for n in self.data.names}


def _case_rows(case: tuple[str, str], amplitude: float) -> list[list[str]]:
    example, variant = case
    channel_inputs, truth_form = CASES[case]
    sets = [s for s in example_data_sets(example) if s.variant.key == variant]
    paths, _ = cached_data(sets)
    by_role = {s.cycle.role: p for s, p in zip(sets, paths)}
    fmu = example_fmu(example)
    info = read_model_info(fmu)
    train_data = read_data(by_role["train"], info)
    aliases = {}
    for channel in channel_inputs:
        aliases.update(workflow.channel_aliases(fmu, info, channel, train_data.start_values, train_data.time,
                                                train_data.start, train_data.start + workflow.ALIAS_SPAN))
    truth_parameters = sets[0].variant.truth_parameters
    train = _Run(by_role["train"], info, truth_parameters, aliases)
    test = _Run(by_role["test"], info, truth_parameters, aliases)
    truth = example_fmu(sets[0].variant.fmu)
    families = [("ANN's last layer", _ann_family(truth, train, channel_inputs))]
    if truth_form:
        families.append(("the truth's form " + " + ".join(f"{b.replace('w', v)}" for v, b in truth_form),
                         _term_family(truth, train, channel_inputs, truth_form)))
    rows, checked = [], []
    for label, family in families:
        try:
            responses = {name: _responses(family, run, amplitude) for name, run in (("train", train), ("test", test))}
            hidden = _hidden_metrics(train.data, responses["train"])
            counts = sorted({k for k in SHAPES if k < family.count} | {family.count})
            brackets = [_largest_rises(test.data, responses["test"], hidden, family.strongest(k)) for k in counts]
            for index, k in enumerate(counts):
                # the shape sets are nested: a change of fewer shapes is one of more
                cells = ", ".join(f"{name} {max(b[name][0] for b in brackets[:index + 1]):.3g}-"
                                  f"{min(b[name][1] for b in brackets[index:]):.3g}" for name in test.data.names)
                rows.append([f"{example} {variant}", label, f"{len(family.strongest(k))} of {family.count}", cells])
            if not checked:
                checked = _check(family, train, test, responses, hidden)
        finally:
            family.close()
    for line in checked:
        print(f"  {example} {variant}: {line}", flush=True)
    return rows


def _check(family, train: _Run, test: _Run, responses: dict, hidden: list[np.ndarray]) -> list[str]:
    """The truth, and the truth with the change that moves the test signal of the largest rise most
    (all shapes, at the edge of hidden by the linear responses), shrunk until the simulation itself
    raises no signal's MSE / noise variance on the fit part or the validation tail by more than the
    noise's spread (the responses are linear only near the truth): MSE / noise variance per role and
    signal, as simulated."""
    rises = _largest_rises(test.data, responses["test"], hidden, list(range(family.count)))
    signal = max(rises, key=lambda name: rises[name][0])
    worst = rises[signal][2]
    split = _split(train.data)
    parts = {"fit part": train.data.time <= split, "validation tail": train.data.time > split}
    allowed = {role: score_spread([train.data.time[rows]], 1) for role, rows in parts.items()}

    def ratios(run: _Run, rows) -> dict:
        predicted = run.signals(family.model)
        return {n: float(np.mean((predicted[n][rows] - run.data.signals[n][rows]) ** 2) / run.data.noise_variance(n))
                for n in run.data.names}

    def line(label: str, train_ratios: dict, test_ratios: dict) -> str:
        cells = {**train_ratios, "test": test_ratios}
        return f"{label}: " + "; ".join(f"{role} " + ", ".join(f"{n} {v:.3g}" for n, v in values.items())
                                        for role, values in cells.items())
    family.set(None)
    truth = {role: ratios(train, rows) for role, rows in parts.items()}
    lines = [line("truth FMU", truth, ratios(test, np.ones(test.data.time.size, dtype=bool)))]
    shrink = 1.0
    for _ in range(CHECK_SHRINKS):
        family.set(shrink * worst)
        changed = {role: ratios(train, rows) for role, rows in parts.items()}
        if all(changed[role][n] - truth[role][n] <= allowed[role] for role in parts for n in changed[role]):
            tested = ratios(test, np.ones(test.data.time.size, dtype=bool))
            lines.append(line(f"truth FMU + a hidden change ({shrink:.3g} of the linear edge, of most test {signal})",
                              changed, tested))
            break
        shrink *= 0.7
    else:
        lines.append(f"no hidden change found within {CHECK_SHRINKS} shrinks")
    family.set(None)
    return lines


def _split(data) -> float:
    return data.start + (1.0 - workflow.VALIDATION_SHARE) * (data.stop - data.start)


class _Family:
    """Shapes of the correction on `model`: set(sizes) makes the correction the sum of sizes[k] times
    shape k (in units of its channel derivative's spread), set(None) removes it."""

    def __init__(self, model: NeuralFMU, count: int, setter, channel_of: list[int]):
        self.model, self.count, self._setter, self.channel_of = model, count, setter, channel_of

    def set(self, sizes) -> None:
        self._setter(np.zeros(self.count) if sizes is None else np.asarray(sizes, dtype=float))

    def strongest(self, k: int) -> list[int]:
        """The first k shapes of each channel (each channel's shapes come strongest first)."""
        seen: dict[int, int] = {}
        keep = []
        for index, channel in enumerate(self.channel_of):
            seen[channel] = seen.get(channel, 0) + 1
            if seen[channel] <= k:
                keep.append(index)
        return keep

    def close(self) -> None:
        self.model.close()


def _base_samples(fmu, train: _Run, names: list[str]) -> dict:
    """The base model's values of `names` along the training run."""
    model = NeuralFMU(fmu, TopologyConfig(), start_values=train.start_values)
    try:
        run = simulate_over(model, train.data, STEP, "rk4", train.start_values, plain=True, record=names)
    finally:
        model.close()
    return {name: np.asarray(run[name], dtype=float) for name in names}


def _ann_family(fmu, train: _Run, channel_inputs: dict) -> _Family:
    channels = list(channel_inputs)
    inputs = list(dict.fromkeys(n for names in channel_inputs.values() for n in names))
    torch.manual_seed(0)
    config = TopologyConfig(channels=channels, inputs=inputs, kind="residual", hidden=[16, 16],
                            channel_inputs=[channel_inputs[c] for c in channels] if len(channels) > 1 else [])
    model = NeuralFMU(fmu, config, start_values=train.start_values)
    topology = model.topology
    plain = _base_samples(fmu, train, [*inputs, *channels])
    x = np.stack([plain[n] for n in inputs], axis=1)
    topology.initialise_scaling(x, np.stack([plain[c] for c in channels], axis=1))
    free = topology.last_layer_free()
    directions = _directions(topology, x, free.numpy())        # columns: per channel, strongest first
    n_weights = int(free.sum())
    owner = np.repeat(np.arange(len(channels)), free.numpy().sum(axis=1))     # the channel of each free entry
    channel_of = [int(owner[np.argmax(np.abs(column[:n_weights]))]) for column in directions.T]
    layer = topology.ann[-1]

    def setter(sizes):
        entries = directions @ sizes
        with torch.no_grad():
            weight = torch.zeros_like(layer.weight)
            weight[free] = torch.from_numpy(entries[:n_weights])
            layer.weight.copy_(weight)
            layer.bias.copy_(torch.from_numpy(entries[n_weights:]))
    family = _Family(model, directions.shape[1], setter, channel_of)
    family.set(None)
    return family


def _term_family(fmu, train: _Run, channel_inputs: dict, form: list[tuple[str, str]]) -> _Family:
    (channel, _), = channel_inputs.items()
    variables = list(dict.fromkeys(v for v, _ in form))
    plain = _base_samples(fmu, train, [*variables, channel])
    spread = float(np.std(plain[channel]))
    bases = {"w": lambda w: w, "w*|w|": lambda w: w * np.abs(w), "w^2": lambda w: w * w}
    # each term of unit coefficient scaled to the derivative's spread along the training run
    units = [spread / math.sqrt(float(np.mean(bases[b](plain[v]) ** 2))) for v, b in form]
    terms = [{"variable": v, "basis": b, "center": 0.0, "coefficient": u, "form": b} for (v, b), u in zip(form, units)]
    model = NeuralFMU(fmu, TopologyConfig(channels=[channel], inputs=variables, kind="residual", base_terms=terms),
                      start_values=train.start_values)
    weights = model.topology.base.weights.clone()

    def setter(sizes):
        with torch.no_grad():
            model.topology.base.weights.copy_(weights * torch.from_numpy(sizes)[None, :, None])
    family = _Family(model, len(form), setter, [0] * len(form))
    family.set(None)
    return family


def _responses(family: _Family, run: _Run, amplitude: float) -> list[dict]:
    """Per shape: {signal: d(signal at the samples) / d(size)} by central differences."""
    columns = []
    for k in range(family.count):
        sizes = np.zeros(family.count)
        sizes[k] = amplitude
        family.set(sizes)
        up = run.signals(family.model)
        family.set(-sizes)
        down = run.signals(family.model)
        columns.append({n: (up[n] - down[n]) / (2 * amplitude) for n in run.data.names})
    family.set(None)
    return columns


def _hidden_metrics(data, responses: list[dict]) -> list[np.ndarray]:
    """One H_j per part (fit part, validation tail) and signal, with c^T H_j c the rise of that MSE /
    noise variance over its allowance (the noise's spread there) for the changes c of the shapes'
    sizes: a change is hidden when every c^T H_j c <= 1."""
    split = _split(data)
    metrics = []
    for rows in (data.time <= split, data.time > split):
        allowed = score_spread([data.time[rows]], 1)
        for name in data.names:
            block = np.column_stack([c[name][rows] for c in responses])
            metrics.append(np.atleast_2d(block.T @ block / (rows.sum() * data.noise_variance(name) * allowed)))
    return metrics


def _largest_rises(data, responses: list[dict], hidden: list[np.ndarray], keep: list[int]) -> dict:
    """Per test signal (G: the rise of its MSE / noise variance, c^T G c, where the model errs only by
    noise) the largest c^T G c over the hidden changes among the shapes `keep`, bracketed: (reached,
    at most, the sizes of all shapes that reach it). At most: the smallest largest eigenvalue of G
    against sum_j w_j H_j over weights w_j >= 0 summing to 1, since every such ellipsoid holds the
    hidden set (the S-lemma's dual, a convex problem in w); reached: by that eigenvector, scaled to
    the edge of the hidden set (or the eigenvector against their sum, where it reaches further)."""
    parts = [h[np.ix_(keep, keep)] for h in hidden]
    rises = {}
    for name in data.names:
        block = np.column_stack([responses[k][name] for k in keep])
        gain = block.T @ block / (block.shape[0] * data.noise_variance(name))
        bound, direction = _upper_bound(gain, parts)
        # the bound's eigenvector, or the one against the sum of the parts, whichever reaches further
        candidates = [direction, eigh(gain, _regularised(sum(parts)))[1][:, -1]]
        candidates = [c / math.sqrt(max(float(c @ h @ c) for h in parts)) for c in candidates]
        direction = max(candidates, key=lambda c: float(c @ gain @ c))
        sizes = np.zeros(len(responses))
        sizes[keep] = direction
        rises[name] = (float(direction @ gain @ direction), bound, sizes)
    return rises


def _upper_bound(gain: np.ndarray, parts: list[np.ndarray]) -> tuple[float, np.ndarray]:
    """(min over the weights w of the largest eigenvalue of gain against sum_j w_j parts_j, its
    eigenvector): w the softmax of z, L-BFGS on log(eigenvalue) with its gradient in w,
    -c^T part_j c / c^T (sum w part) c for the eigenvector c, from equal weights."""
    def largest(z):
        w = np.exp(z - z.max())
        w /= w.sum()
        metric = _regularised(sum(wj * h for wj, h in zip(w, parts)))
        values, vectors = eigh(gain, metric)
        c = vectors[:, -1]
        by_weight = -np.array([c @ h @ c for h in parts]) / (c @ metric @ c)
        return math.log(max(float(values[-1]), 1e-300)), w * (by_weight - w @ by_weight), c
    start = np.zeros(len(parts))
    found = minimize(lambda z: largest(z)[:2], start, jac=True, method="L-BFGS-B", options={"maxiter": 500})
    best = min((start, found.x), key=lambda z: largest(z)[0])
    value, _, vector = largest(best)
    return (math.exp(value) if value > math.log(1e-300) else 0.0), vector


def _regularised(metric: np.ndarray) -> np.ndarray:
    """The metric with a ridge of 1e-12 of its mean diagonal: shapes the data do not see at all stay
    finite (their rise is then what the ridge allows, enormous, as it should read)."""
    return metric + 1e-12 * np.trace(metric) / len(metric) * np.eye(len(metric))


if __name__ == "__main__":
    main()
