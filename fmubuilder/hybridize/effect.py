"""The effect a hybrid adds, drawn against its inputs: what the chosen candidate learned and, where
the data were made by a known "truth" model, what the truth adds; one Effect per corrected
derivative, against the inputs its output reads (probed on the network: a sub-network per
derivative reads only its own).

Both are evaluated along one run of the declared FMU over the training data (its states and the
term's input variables every few samples):

    learned(t) = p_ann[c] * net(u(t))[c]                    the exported network or fitted term
    truth(t)   = f_truth(x(t), t)[c] - f_declared(x(t), t)[c]   derivatives of channel c at the same
                                                            state, inputs and time

With a truth, both are drawn along the declared run: the inputs and the declared FMU's derivative
are the run's, the truth's derivative comes from the truth following the run, every state set to
the run's after every step (neural/collocation.forced_run). A sampled controller then updates at
its ticks from the same states as in the run. Set to a state at single points instead, an FMU
keeps its discrete states where they started (the VLDM's driver: a throttle of 0, no motor torque,
and no extra loss drawn where the truth adds 0.77 kW rms). A state event inside a step is found on
the step's own course (solve.py, indicators_at_end), as the run found it.

The truth is the FMU the data's sidecar names (`truth_model`, checked by its sha256, with the
sidecar's `truth` parameters); it is found only when it is one of the bundled examples. Without it
the plot shows the learned term alone, along the declared FMU's own run.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..data import read_sidecar
from ..errors import FmuBuilderError
from ..export.network import OnnxNetwork
from ..export.spec import HybridSpec
from ..files import file_sha256
from ..fmi import read_model_info
from .evaluate import Scoring, simulate_over

# Points of the declared FMU's run at which the effects are evaluated.
EFFECT_POINTS = 600
# An output reads an input when moving the input by this share of its range moves the output by more
# than READS_ABOVE of the output's largest value at some point.
PROBE_SHIFT = 1e-3
READS_ABOVE = 1e-9


@dataclass
class Effect:
    channel: str                          # der(x) the term corrects
    kind: str                             # "network" or "fitted term"
    inputs: dict[str, np.ndarray]         # the term's input variables along the run
    learned: np.ndarray                   # the correction the hybrid adds to the channel
    truth: np.ndarray | None = None       # what the truth model adds (None: unknown)
    truth_source: str = ""                # where the truth came from, or why there is none


def effects_of(spec_path: Path, declared_fmu: Path, data, start_values: dict, scoring: Scoring) -> list[Effect]:
    """The learned (and, if known, true) effect on each of the hybrid's channels along the declared
    FMU's run over `data`, simulated as every model is scored (`scoring`)."""
    spec = HybridSpec.load(spec_path)
    points, truth = None, None
    try:
        truth_fmu, parameters, truth_source = _truth_model(data)
        if truth_fmu is not None:
            points, truth = followed_effect(truth_fmu, declared_fmu, spec.inputs, spec.channels, data, start_values,
                                            parameters, scoring)
    except FmuBuilderError as exc:
        truth_source = f"the truth could not be evaluated ({exc})"
    if points is None:
        interval = max(scoring.step, (data.stop - data.start) / EFFECT_POINTS)
        run = simulate_over(declared_fmu, data, start_values, spec.inputs, scoring, output_interval=interval,
                            record_events=False)
        points = {name: np.asarray(run[name], dtype=float) for name in spec.inputs}
    network = OnnxNetwork(spec.onnx)
    rows = np.column_stack([points[name] for name in spec.inputs])
    outputs = np.array([network(row) for row in rows])
    learned = outputs * np.asarray(spec.p_ann)
    reads = inputs_read(network, rows, outputs)
    return [Effect(channel, spec.term, {name: points[name] for i, name in enumerate(spec.inputs) if reads[j, i]},
                   learned[:, j], None if truth is None else truth[:, j], truth_source)
            for j, channel in enumerate(spec.channels)]


def inputs_read(network, rows: np.ndarray, base: np.ndarray | None = None) -> np.ndarray:
    """[outputs, inputs] whether each output of `network` moves with each input at the points `rows`
    [N, inputs] (`base`: the network's outputs there, if already known); an output that moves with
    none is shown against all."""
    if base is None:
        base = np.array([network(row) for row in rows])
    size = np.maximum(np.abs(base).max(axis=0), np.finfo(float).tiny)
    reads = np.zeros((base.shape[1], rows.shape[1]), dtype=bool)
    for i in range(rows.shape[1]):
        shifted = rows.copy()
        column = rows[:, i]
        shifted[:, i] += PROBE_SHIFT * (np.ptp(column) or max(abs(float(column.mean())), 1.0))
        moved = np.abs(np.array([network(row) for row in shifted]) - base).max(axis=0)
        reads[:, i] = moved > READS_ABOVE * size
    reads[~reads.any(axis=1)] = True
    return reads


def followed_effect(truth_fmu: Path, declared_fmu: Path, inputs: list[str], channels: list[str], data,
                    start_values: dict, parameters: dict, scoring: Scoring) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """({input: values}, [points, channels] f_truth - f_declared) at about EFFECT_POINTS points of
    the declared FMU's run over `data`, the truth following it (the module docstring; the declared
    FMU followed along its own run gives that run's values, so they are read from the run); the
    truth starts with its `parameters` on top of `start_values`."""
    states = [s.name for s in read_model_info(declared_fmu).states]
    if [s.name for s in read_model_info(truth_fmu).states] != states:
        raise FmuBuilderError("its continuous states are not the declared FMU's")
    run = simulate_over(declared_fmu, data, start_values, dict.fromkeys([*states, *inputs, *channels]), scoring,
                        record_events=False)
    grid = np.asarray(run.time, dtype=float)
    columns = [np.asarray(run[name], dtype=float) for name in states]

    def along_run(t):
        t = np.atleast_1d(np.asarray(t, dtype=float))
        return np.stack([np.interp(t, grid, column) for column in columns], axis=1)
    times, truth = _following(truth_fmu, data, {**start_values, **parameters}, scoring, states, along_run, channels)
    points = np.arange(0, len(grid), max(1, len(grid) // EFFECT_POINTS))
    at = grid[points]
    return ({name: np.asarray(run[name], dtype=float)[points] for name in inputs},
            np.stack([np.interp(at, times, truth[c]) - np.asarray(run[c], dtype=float)[points] for c in channels],
                     axis=1))


def _following(fmu_path: Path, data, start_values: dict, scoring: Scoring, states: list[str], along_run,
               record: list[str]) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(the scoring grid's times, {name: values there}) of the FMU run over `data` with every state
    set to along_run(t) after every step."""
    from ..neural import NeuralFMU, TopologyConfig
    from ..neural.collocation import forced_run
    model = NeuralFMU(fmu_path, TopologyConfig(), start_values=start_values)
    try:
        solver = scoring.solver if scoring.solver in ("euler", "rk4") else "rk4"   # the states are set every step
        trajectory = forced_run(model, data, scoring.step, solver, states, along_run, list(dict.fromkeys(record)),
                                data.input_signals(model.info))
        return data.start + np.asarray(trajectory.times, dtype=float), \
            {name: trajectory.numpy(name)[:, 0] for name in record}
    finally:
        model.close()


def _truth_model(data) -> tuple[Path | None, dict, str]:
    """The bundled example FMU that made the data (by the sidecar's name and sha256), its parameters."""
    from ..build import example_fmu, list_examples
    sidecar = read_sidecar(data.path) if data.path else None
    model = (sidecar or {}).get("truth_model") or {}
    name = Path(str(model.get("file", ""))).stem
    if not name:
        return None, {}, "the data name no truth model"
    if name not in list_examples():
        return None, {}, f"the truth model {name} is not a bundled example"
    fmu = example_fmu(name)
    if model.get("sha256") and file_sha256(fmu) != model["sha256"]:
        return None, {}, f"the bundled {name} differs from the one that made the data"
    parameters = dict(((sidecar.get("truth") or {}).get("parameters")) or {})
    return fmu, parameters, f"{name}.fmu" + (f" with {_listed(parameters)}" if parameters else "")


def _listed(values: dict) -> str:
    return ", ".join(f"{k} = {v:g}" if isinstance(v, (int, float)) else f"{k} = {v}" for k, v in values.items())
